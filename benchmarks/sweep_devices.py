"""A small sweep with `sharded_vmap` on 1 vs N forced host devices (CPU).

    XLA_FLAGS=--xla_force_host_platform_device_count=1 python benchmarks/sweep_devices.py
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/sweep_devices.py

The device count is fixed when JAX starts, so each count is its own process. Prints the
median wall and CPU time of a 8x8 speed x clearance sweep (72 nodes x 72 steps/rev, 2000
revolutions, M = 100, `lax.map` on each device) after a warm-up call.
"""

import statistics
import time

import jax
import numpy as np

import jaxwear as jw
from jaxwear._core.parallel import sharded_vmap
from jaxwear._physics.wear import build_schedule, wear_loop

p = jw.preset("rig")
cfg = jw.ModelConfig(nodes=72, steps_per_rev=72)
sched = build_schedule(p, cfg, revolutions=2000, M=100, pad=False)


def point(speed, clearance):
    return wear_loop(p.with_values({"speed_rpm": speed, "clearance_mm": clearance}), cfg,
                     sched).depth


if __name__ == "__main__":
    S, C = np.meshgrid(np.linspace(148, 276, 8) * 2 * np.pi / 60,
                       np.linspace(0.05, 0.15, 8) * 1e-3, indexing="ij")
    S, C = S.ravel(), C.ravel()
    sharded_vmap(point, (S, C), method="map")
    wall, cpu = [], []
    for _ in range(5):
        t0, c0 = time.perf_counter(), time.process_time()
        sharded_vmap(point, (S, C), method="map")
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"{jax.device_count()} device(s), {S.size} points: wall "
          f"{statistics.median(wall):.3f} s, cpu {statistics.median(cpu):.3f} s (medians of 5)")
