"""Write the full-coverage plans (thesis-full.yaml, demo-full.yaml) from one description.

Every one of the thirty motion-error terms gets its Table 5.3 setup (laser optics, proximity
reference surface), and each setup runs the staged single-heat-source test of ch. 4.3/5.2 on its
own: a cold baseline, the spindle alone, a cool-down, the measured axis' own drive alone, a
cool-down. The setup changes between tests, as on the real machine, and the laser is zeroed at
each new setup. The last stages run spindle and feed together on the three positioning setups
(the combined stages that validate the model, ch. 6.4). Regenerate after editing:

    python examples/plans/generate_full.py
"""

from __future__ import annotations

from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
#: travel of the five-axis machine (Tables A.3, A.4): mm, degrees
TRAVEL = {"X": [0.0, 254.0], "Y": [0.0, 254.0], "Z": [-254.0, 0.0], "A": [-45.0, 45.0], "B": [-45.0, 45.0]}
POSITIONS = {
    "X": [0.0, 63.5, 127.0, 190.5, 254.0],
    "Y": [0.0, 63.5, 127.0, 190.5, 254.0],
    "Z": [-254.0, -190.5, -127.0, -63.5, 0.0],
    "A": [-40.0, -20.0, 0.0, 20.0, 40.0],
    "B": [-40.0, -20.0, 0.0, 20.0, 40.0],
}
#: the thesis machine's stated lengths for table 6.3's physical check (docs/bundle.md, machine.geometry)
GEOMETRY = {
    "source": "thesis appendix A, Table A.1; ch. 3.5 (spindle arm L 400 mm, H 200 mm; ballscrews l 150 mm)",
    "alpha_c_per_degC": 1.21e-05,
    "links_mm": {
        "spindle_head": [0.0, -400.0, -200.0],
        "column": [0.0, 400.0, 1200.0],
        "carriage": [0.0, 0.0, -200.0],
        "table": [0.0, 0.0, -200.0],
        "rotary_support": [0.0, 0.0, -200.0],
        "part_table": [0.0, 0.0, -400.0],
    },
    "screw_fixed_mm": {"X": 150.0, "Y": 150.0, "Z": 150.0},
    "bending": {
        "spindle_arm": {
            "length_mm": 400.0,
            "height_mm": 200.0,
            "across": "upper-lower",
            "angle": "alpha",
            "deflection": "dz",
        }
    },
}
#: oscillation of each axis' own drive (its motor, screw or gear train warms up)
FEED = {
    "X": (4000, 0.0, 254.0),
    "Y": (4000, 0.0, 254.0),
    "Z": (4000, -254.0, 0.0),
    "A": (2000, -40.0, 40.0),
    "B": (2000, -40.0, 40.0),
}

# Table 5.3, one setup per laser alignment (figs. 5.7-5.9) and one per proximity fixture (figs. 5.11-5.13)
SETUPS: dict[str, dict] = {}
for ax, own, straight, angles, roll in (
    ("X", "dx", ("dy", "dz"), ("beta", "gamma"), "alpha"),
    ("Y", "dy", ("dx", "dz"), ("alpha", "gamma"), "beta"),
    ("Z", "dz", ("dx", "dy"), ("alpha", "beta"), "gamma"),
):
    k = ax.lower()
    SETUPS[f"{k}-position"] = {"instrument": "laser", "optics": "linear", "axis": ax, "terms": [own]}
    for t in straight:
        SETUPS[f"{k}-straightness-{t[1]}"] = {"instrument": "laser", "optics": "straightness", "axis": ax, "terms": [t]}
    SETUPS[f"{k}-pitch"] = {"instrument": "laser", "optics": "angular", "axis": ax, "terms": [angles[0]]}
    SETUPS[f"{k}-yaw"] = {"instrument": "laser", "optics": "angular", "axis": ax, "terms": [angles[1]]}
    SETUPS[f"{k}-roll"] = {
        "instrument": "proximity",
        "fixture": "reference_edge",
        "axis": ax,
        "terms": [roll],
        "reference": {"artefact": "two parallel reference lines, fig. 5.11"},
    }
SETUPS["a-position"] = {
    "instrument": "laser",
    "optics": "angular",
    "axis": "A",
    "terms": ["alpha"],
    "counter_rotating": True,
    "reference": {"fixture": "counter-rotating table, fig. 5.10"},
}
SETUPS["a-runout"] = {
    "instrument": "proximity",
    "fixture": "cylinder",
    "axis": "A",
    "terms": ["dx", "dy", "dz", "beta", "gamma"],
    "reference": {"artefact": "reference arcs on the A axis, fig. 5.12, table C.1"},
}
SETUPS["b-position"] = {
    "instrument": "laser",
    "optics": "angular",
    "axis": "B",
    "terms": ["beta"],
    "counter_rotating": True,
    "reference": {"fixture": "counter-rotating table, fig. 5.10"},
}
SETUPS["b-runout"] = {
    "instrument": "proximity",
    "fixture": "cylinder",
    "axis": "B",
    "terms": ["dx", "dy", "dz", "alpha", "gamma"],
    "reference": {"artefact": "reference cylinder on the B table, fig. 5.13, table C.2"},
}


def plan(
    name: str, description: str, hours: dict[str, float], scan_s: float, sweep_s: float, combined_h: float
) -> dict:
    """Return a full-coverage plan: every setup through baseline, spindle, cool, own feed, cool."""
    stages = []
    # the setups that read against a stable artefact (proximity arrays) go first, on the cold machine:
    # a laser is zeroed when mounted, so only these tie the errors to the cold state the model starts from
    order = sorted(SETUPS, key=lambda sid: SETUPS[sid]["instrument"] != "proximity")
    for sid in order:
        st = SETUPS[sid]
        ax = st["axis"]
        sweep = {"positions": POSITIONS[ax], "interval_s": sweep_s, "point_s": 6, "samples": 10}
        feed, lo, hi = FEED[ax]
        for part, heat in (
            ("base", []),
            ("spindle", [{"kind": "spindle", "rpm": 10000}]),
            ("cool1", []),
            ("feed", [{"kind": "axis", "axis": ax, "feed_mm_min": feed, "from_pos": lo, "to_pos": hi}]),
            ("cool2", []),
        ):
            stages.append(
                {
                    "name": f"{sid}.{part}",
                    "heat": heat,
                    "axis": ax,
                    "setup": sid,
                    "duration_s": hours[part] * 3600,
                    "sweep": sweep,
                }
            )
    for sid in ("x-position", "y-position", "z-position"):
        ax = SETUPS[sid]["axis"]
        feed, lo, hi = FEED[ax]
        sweep = {"positions": POSITIONS[ax], "interval_s": sweep_s, "point_s": 6, "samples": 10}
        stages.append(
            {
                "name": f"{sid}.spindle+feed",
                "axis": ax,
                "setup": sid,
                "duration_s": combined_h * 3600,
                "heat": [
                    {"kind": "spindle", "rpm": 10000},
                    {"kind": "axis", "axis": ax, "feed_mm_min": feed, "from_pos": lo, "to_pos": hi},
                ],
                "sweep": sweep,
            }
        )
        stages.append(
            {
                "name": f"{sid}.cool3",
                "axis": ax,
                "setup": sid,
                "duration_s": combined_h * 1800,
                "heat": [],
                "sweep": sweep,
            }
        )
    return {
        "format": "driftlab-plan/1",
        "name": name,
        "description": description,
        "machine": {"id": "vmc-5ax-01", "channels": "from scenario", "travel": TRAVEL, "geometry": GEOMETRY},
        "scan_interval_s": scan_s,
        "setups": SETUPS,
        "stages": stages,
    }


def main() -> None:
    """Write both plans next to this script."""
    full = plan(
        "thesis-full",
        "the staged single-heat-source campaign of ch. 5-6 covering all thirty terms",
        {"base": 0.5, "spindle": 2.0, "cool1": 1.5, "feed": 2.0, "cool2": 1.5},
        60,
        1800,
        3.0,
    )
    demo = plan(
        "demo-full",
        "compressed full-coverage campaign for driftlab demo",
        {"base": 0.25, "spindle": 1.0, "cool1": 0.5, "feed": 1.0, "cool2": 0.5},
        120,
        900,
        2.0,
    )
    for doc, head in ((full, "about a week of machine time"), (demo, "about two and a half simulated days")):
        text = yaml.safe_dump(doc, sort_keys=False, width=120)
        note = (
            f"# {doc['description']}: {head}.\n# Generated by examples/plans/generate_full.py "
            "(edit that, then regenerate). `driftlab plan check` shows its coverage.\n"
        )
        (HERE / f"{doc['name']}.yaml").write_text(note + text)


if __name__ == "__main__":
    main()
