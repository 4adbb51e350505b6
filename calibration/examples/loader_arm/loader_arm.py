"""The boom pivot of a wheel loader: its load and motion from a small multibody computation.

Writes the two load files of `study.toml` (the format of design.md §2, preset "load_history"):

- `work.csv`: one 12 s load-and-carry work cycle: fill the bucket at the pile (the boom
  down at -30°), lift to +45° in 5 s, dump, lower empty in 3.5 s;
- `carry.csv`: travel with a loaded bucket held at -10° over rough ground (0.8 s period):
  the frame bounces (±0.3 g vertical) and the boom pitches ±1.5° on the lift cylinders'
  oil compliance, a small oscillation under a large load (fretting-like sliding);

and `loads.png` (the pin load over each cycle). Plain numpy, rigid bodies, d'Alembert.

    python calibration/examples/loader_arm/loader_arm.py [--out FOLDER]

The mechanism (SI units; x forward, y up; the frame pin O at the origin):

- the boom (both arms together): a uniform bar O→P of length L = 2.6 m and mass 550 kg,
  turning about O by the boom angle θ(t) from the horizontal;
- the bucket (450 kg) and its payload (1600 kg, about 0.9 m³ of gravel) as a point mass at
  the boom tip P (their own rotation is left out: the bucket's tilt linkage carries its
  moment to the boom near P);
- the two lift cylinders as one, from the frame point C = (0.5, -0.6) m to the boom point
  D, 0.8 m along the boom and 0.2 m below its axis; each pushes along its own axis only
  (a two-force member: its mass is left out).

Prescribed motion (the operator's, kinematic driving): cycloidal rises θ = θ0 + Δθ
(τ - sin 2πτ / 2π), so that the angular acceleration is finite and zero at both ends.

d'Alembert, for the boom with the bucket as one rigid body turning about O, with the inertia
forces -m a of every mass and the frame's vertical acceleration a_f added to gravity
(g_eff = g + a_f, the frame's inertia on everything it carries):
- moments about O: F_c (D x û)_z + Σ m (r x (-g_eff ŷ - a))_z - I_G θ̈ = 0 gives the
  cylinder force F_c (û the cylinder's direction C→D, a = θ̈ ẑ x r - θ̇² r at each mass's
  position r, I_G = m L²/12 the boom's own inertia about its centre);
- forces: R + F_c û + Σ m (-g_eff ŷ - a) = 0 gives R, the force of the frame's pin on the
  boom: the load on the bushing in the boom eye.
Two boom arms share it equally (a pin and a bushing each; the study's joint is one of them),
so each file holds R / 2. The bushing turns with the boom: its frame is the boom's, the
load is R / 2 turned by -θ, and the pin's rotation relative to the bushing is -(θ - θ(0)).

Assumptions a designer would check: rigid bodies (no frame or boom flexibility), no friction
in the cylinder and its pins, the payload held rigidly, a smooth operator; the carry bounce
is a single harmonic. Only the pin load's size and direction and the boom's rotation leave
this script: replace it by your multibody program's output in the same four columns.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

G = 9.81
L, M_BOOM, M_BUCKET, M_LOAD = 2.6, 550.0, 450.0, 1600.0
C = np.array([0.5, -0.6])  # lift cylinder's frame anchor [m]
D_ALONG, D_BELOW = 0.8, 0.2  # its boom anchor: along the boom axis, below it [m]
ARMS = 2  # boom arms, a pivot pin and bushing each


def cycloid(t, t0, duration, a0, a1):
    """Angle, rate and acceleration of a cycloidal move a0 → a1 over [t0, t0 + duration]."""
    tau = np.clip((t - t0) / duration, 0.0, 1.0)
    inside = (t >= t0) & (t <= t0 + duration)
    d = a1 - a0
    ang = a0 + d * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
    rate = np.where(inside, d / duration * (1 - np.cos(2 * np.pi * tau)), 0.0)
    acc = np.where(inside, d / duration**2 * 2 * np.pi * np.sin(2 * np.pi * tau), 0.0)
    return ang, rate, acc


def work_cycle(t):
    """θ, θ', θ'' [rad, rad/s, rad/s²] and the payload [kg] of the 12 s work cycle."""
    dig, dump = np.radians(-30.0), np.radians(45.0)
    th, w, a = np.full_like(t, dig), np.zeros_like(t), np.zeros_like(t)
    for t0, dur, a0, a1 in ((2.0, 5.0, dig, dump), (8.5, 3.5, dump, dig)):
        ang, rate, acc = cycloid(t, t0, dur, a0, a1)
        m = (t >= t0) & (t <= t0 + dur)
        th, w, a = np.where(m, ang, th), np.where(m, rate, w), np.where(m, acc, a)
    th = np.where((t > 7.0) & (t < 8.5), dump, th)  # the dump dwell
    payload = np.where((t >= 1.0) & (t < 7.5), M_LOAD, 0.0)  # filled at 1 s, dumped at 7.5 s
    return th, w, a, payload, np.zeros_like(t)


def carry_cycle(t, period=0.8):
    """θ, θ', θ'', payload and the frame's vertical acceleration of the carry cycle."""
    w0 = 2 * np.pi / period
    amp = np.radians(1.5)
    th = np.radians(-10.0) + amp * np.sin(w0 * t)
    frame_acc = 0.3 * G * np.sin(w0 * t + 0.6)  # the boom lags the frame's bounce
    return (th, amp * w0 * np.cos(w0 * t), -amp * w0**2 * np.sin(w0 * t),
            np.full_like(t, M_LOAD), frame_acc)


def cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def pin_load(th, w, a, payload, frame_acc):
    """The force of the frame's pin on the boom [N] (rows, 2), ground frame, and the lift
    cylinder force [N] (rows,), by d'Alembert (module docstring)."""
    e = np.stack([np.cos(th), np.sin(th)], 1)  # along the boom
    n = np.stack([-np.sin(th), np.cos(th)], 1)  # normal to it
    masses = [(M_BOOM, 0.5 * L * e), (M_BUCKET + payload, L * e)]
    g_eff = G + frame_acc
    force = np.zeros_like(e)
    moment = np.zeros(len(th))
    for m, r in masses:
        m = np.broadcast_to(m, th.shape)
        acc = a[:, None] * np.stack([-r[:, 1], r[:, 0]], 1) - (w**2)[:, None] * r
        f = m[:, None] * (np.stack([np.zeros_like(th), -g_eff], 1) - acc)  # weight + inertia
        force += f
        moment += cross(r, f)
    moment -= M_BOOM * L**2 / 12 * a  # the boom's own inertia couple about its centre
    d = D_ALONG * e - D_BELOW * n
    u = (d - C) / np.linalg.norm(d - C, axis=1)[:, None]
    f_cyl = -moment / cross(d, u)
    reaction = -(force + f_cyl[:, None] * u)
    return reaction, f_cyl


def load_file(t, th, reaction):
    """Rows of the load file: time, the load on one bushing in the boom's frame, the pin's
    rotation relative to the bushing [deg]."""
    per_pin = reaction / ARMS
    c, s = np.cos(-th), np.sin(-th)
    bx = c * per_pin[:, 0] - s * per_pin[:, 1]
    by = s * per_pin[:, 0] + c * per_pin[:, 1]
    rel = -np.degrees(th - th[0])
    return np.stack([t, bx, by, rel], 1)


def write(path: Path, rows: np.ndarray):
    with open(path, "w") as f:
        f.write("time_s,load_x_N,load_y_N,angle_deg\n")
        for r in rows:
            f.write(",".join(f"{v:.6g}" for v in r) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(Path(__file__).parent), help="folder for the files")
    ap.add_argument("--no-plot", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cycles = {}
    for name, period, dt, motion in (("work", 12.0, 0.01, work_cycle),
                                     ("carry", 0.8, 0.01, carry_cycle)):
        t = np.arange(0.0, period - 1e-9, dt)
        th, w, a, payload, frame_acc = motion(t)
        reaction, f_cyl = pin_load(th, w, a, payload, frame_acc)
        rows = load_file(t, th, reaction)
        write(out / f"{name}.csv", rows)
        cycles[name] = (t, th, rows, f_cyl)
        mag = np.hypot(rows[:, 1], rows[:, 2])
        print(f"{name}.csv: {len(t)} rows over {period:g} s; pin load per bushing "
              f"{mag.min() / 1e3:.1f}-{mag.max() / 1e3:.1f} kN, boom "
              f"{np.degrees(th.min()):.1f}° to {np.degrees(th.max()):.1f}°, lift cylinders "
              f"up to {f_cyl.max() / 1e3:.0f} kN")
    if not args.no_plot:
        plot(out / "loads.png", cycles)
    return cycles


def plot(path, cycles):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5))
    for row, (name, (t, th, rows, _)) in zip(axes, cycles.items()):
        mag = np.hypot(rows[:, 1], rows[:, 2]) / 1e3
        row[0].plot(t, mag, "k-", label="|load| per bushing [kN]")
        row[0].set_ylabel("pin load [kN]")
        ax2 = row[0].twinx()
        ax2.plot(t, np.degrees(th), "tab:blue", lw=1)
        ax2.set_ylabel("boom angle [deg]", color="tab:blue")
        row[0].set_xlabel("time [s]")
        row[0].set_title(f"{name}.csv: load and boom angle")
        row[1].plot(t, np.degrees(np.arctan2(rows[:, 2], rows[:, 1])), "tab:red", lw=1)
        row[1].set_xlabel("time [s]")
        row[1].set_ylabel("load direction, bushing frame [deg]")
        row[1].set_title(f"{name}.csv: where the pin presses the bore")
        for ax in row:
            ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
