"""LinuxCNC axis compensation file (``[JOINT_n]COMP_FILE``, ``COMP_FILE_TYPE = 1``).

One line per compensation point, ``nominal forward_trim reverse_trim``, nominal positions
ascending. With ``COMP_FILE_TYPE = 1`` the trims are added to the commanded joint position: the
forward trim while the joint moves in the positive direction, the reverse trim while it moves in
the negative direction; between points motion interpolates linearly, beyond the first and last
point the end trim holds. The loader stops at the first line that is not three numbers, so the
file carries no comment lines (the model and temperatures go into the INI comment instead).

Source: LinuxCNC ``src/emc/motion/usrmotintf.cc`` (``usrmotLoadComp``: ``sscanf("%lf %lf %lf")`` per
line, stop at the first line that does not give three numbers; type 1 = trims), ``command.c``
(``EMCMOT_SET_JOINT_COMP``: nominals must increase, at most ``EMCMOT_COMP_SIZE`` = 256 entries, from
``motion.h``), ``control.c`` (``compute_screw_comp``: the forward trim while ``vel_cmd > 0``, the
reverse trim while ``vel_cmd < 0``, linear between entries); docs/src/config/ini-config.adoc.
"""

from __future__ import annotations

from driftlab.compensator.exports.controllers import Controller, Export
from driftlab.compensator.exports.grid import AxisTable

DECIMALS = 7  # 0.1 nm (mm) / 1e-7 deg: far below any table's interpolation error


def write(table: AxisTable, ctl: Controller, joint: int | None = None) -> Export:
    """Return the COMP_FILE text (nominal, forward trim, reverse trim) and the INI settings."""
    lines = [
        f"{p:.{DECIMALS}f} {f:.{DECIMALS}f} {r:.{DECIMALS}f}"
        for p, f, r in zip(table.positions, table.forward, table.reverse)
    ]
    j = "XYZAB".index(table.axis) if joint is None else joint
    settings = {
        f"[JOINT_{j}]COMP_FILE_TYPE": 1,
        f"[JOINT_{j}]COMP_FILE": "<this file>",
        "comment": f"# driftlab thermal compensation of {table.axis}, model {table.model}",
    }
    return Export(ctl.name, {"": "\n".join(lines) + "\n"}, settings)
