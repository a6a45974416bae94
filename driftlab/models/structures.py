"""Which chain element each instrumented structure of the machine belongs to (shared by the fit and its checks).

A chosen term goes to the element where its thermocouples sit (ch. 4: allocation of work-space error
to links): the structures of Table 5.1's sites map to the links and joints of the HTM chain of
Table A.1; the ballscrew sites of each translational joint carry its eq. 3.2 terms.
"""

from __future__ import annotations

from collections.abc import Mapping

#: the element whose structure a thermocouple's structure belongs to (allocation of a chosen term)
STRUCTURE_ELEMENT: Mapping[str, str] = {
    "spindle": "T1",
    "spindle_arm": "T1",
    "z_column": "T2",
    "base": "T2",
    "z_screw": "phi_z",
    "z_motor": "phi_z",
    "y_screw": "phi_y",
    "y_motor": "phi_y",
    "xy_carriage": "T3",
    "x_screw": "phi_x",
    "x_motor": "phi_x",
    "x_table": "T4",
    "rotary_base": "theta_x",
    "a_drive": "theta_x",
    "b_table": "theta_y",
    "b_drive": "theta_y",
}
#: ballscrew sites of each translational joint (eq. 3.2: error ~ position x dT of the screw)
SCREW_STRUCTURES: Mapping[str, tuple[str, ...]] = {
    "phi_x": ("x_screw", "x_motor"),
    "phi_y": ("y_screw", "y_motor"),
    "phi_z": ("z_screw", "z_motor"),
}
#: which translations of its link a structure's material spans (eqs. 3.1, 3.3): a link shared by two
#: structures grows along each component with the structure that spans it, not twice (the column is the
#: T2 link's 1200 mm of Z, the base its run along Y to the table; the arm is T1's 400 mm along Y, the
#: spindle housing its Z). A structure not listed spans all of its link.
STRUCTURE_SPANS: Mapping[str, tuple[str, ...]] = {
    "z_column": ("dz",),
    "base": ("dx", "dy"),
    "spindle_arm": ("dx", "dy"),
    "spindle": ("dz",),
}
