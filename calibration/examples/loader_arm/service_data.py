"""Stand-in service measurements for the loader example: `service.csv` (hours,depth_um).

A fleet's service records would give, at each inspection, the largest radial wear of the
boom-pivot bushing (bore gauge, ±10 µm). This example has none, so this script makes them
from the model, as a careful test would, without the inverse crime: the "true" joint
(K_d 7.0e-16 1/Pa instead of the study's handbook start 1.0e-15, radial clearance 0.104 mm
instead of the nominal 0.10) is computed at twice the study's nodes and steps with a tenth
of its integration tolerance, and Gaussian noise of 10 µm is added. Replace service.csv by
your own inspections (same two columns) and delete this script.

    python calibration/examples/loader_arm/service_data.py   (7 min of CPU: 180 x 144)
"""

from pathlib import Path

import numpy as np

import jaxwear as jw

HERE = Path(__file__).parent
TRUE = {"K_d_per_Pa": 7.0e-16, "clearance_mm": 0.104e-3}  # SI
INSPECTIONS_H = (500.0, 1000.0, 1500.0)
NOISE_UM = 10.0


def main():
    if not (HERE / "service.csv").exists():  # the study names it: a placeholder to load
        (HERE / "service.csv").write_text("hours,depth_um\n500,0\n")
    study = jw.load_study(HERE / "study.toml")
    e = study.experiments[0]
    p = study.params(e).with_values(TRUE)
    fine = study.config.replace(nodes=2 * study.config.nodes,
                                steps_per_rev=2 * study.config.steps_per_rev)
    res = jw.simulate(p, fine, hours=max(INSPECTIONS_H), snapshots=list(INSPECTIONS_H),
                      tolerance_um=study.wear_tolerance_um / 10)
    depth = np.asarray(res.snapshots).max(axis=1) * 1e6
    y = depth + NOISE_UM * np.random.default_rng(7).standard_normal(len(depth))
    with open(HERE / "service.csv", "w") as f:
        f.write("hours,depth_um\n")
        f.writelines(f"{h:g},{v:.0f}\n" for h, v in zip(INSPECTIONS_H, y))
    print("true maximum depth [µm]:", np.round(depth, 1), "-> service.csv:", np.round(y))


if __name__ == "__main__":
    main()
