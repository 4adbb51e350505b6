"""Sharded batches (`jaxwear._core.parallel`): the same numbers as unsharded, on 1, 2 devices and
across 2 processes.

Sharding changes where a point is computed, never how: every point runs the same point
function on its own, so sharded results must equal unsharded ones exactly (same compiled
arithmetic per point, up to the order of batched reductions, hence 1e-12 relative).
Multi-device runs need `XLA_FLAGS=--xla_force_host_platform_device_count=2` set before JAX
starts, so they run in a subprocess; the two-process `jax.distributed` run uses localhost
only, a free port and a hard time limit.
"""

import os
import socket
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxwear._core.parallel import sharded_fn, sharded_vmap


def _point(x, y):
    """A cheap nonlinear point function with a pytree output and a while loop (like the
    contact solver: per-lane iteration counts differ)."""
    def body(s):
        i, v = s
        return i + 1, 0.5 * (v + x / v)

    _, root = jax.lax.while_loop(lambda s: (s[0] < 60) & (jnp.abs(s[1] ** 2 - x) > 1e-14 * x),
                                 body, (0, 1.0 + x))
    return {"root": root, "poly": jnp.stack([x * y, x + y ** 2])}


X = np.linspace(0.5, 40.0, 7)
Y = np.linspace(-1.0, 2.0, 7)


def _expected():
    return {"root": np.sqrt(X), "poly": np.stack([X * Y, X + Y ** 2], axis=1)}


@pytest.mark.parametrize("method", ["vmap", "map"])
@pytest.mark.parametrize("chunk", [None, 2, 100])
def test_matches_unbatched_math(method, chunk):
    """Padding (7 points, chunks of 2 → 8), chunking and pytree outputs are invisible."""
    out = sharded_vmap(_point, (X, Y), method=method, chunk=chunk)
    exp = _expected()
    assert out["root"].shape == (7,) and out["poly"].shape == (7, 2)
    np.testing.assert_allclose(out["root"], exp["root"], rtol=1e-13)
    np.testing.assert_allclose(out["poly"], exp["poly"], rtol=1e-13)


def test_traceable_under_jit_and_autodiff():
    """`sharded_fn` composes with jit and both AD modes: forward mode through the while loop
    (d sqrt(x)/dx = 1/(2 sqrt x)), reverse mode through a loop-free point function."""
    xs, ys = jnp.asarray(X), jnp.asarray(Y)
    jf = jax.jit(jax.jacfwd(lambda x: sharded_fn(_point)(x, ys)["root"]))
    np.testing.assert_allclose(np.diag(np.asarray(jf(xs))), 0.5 / np.sqrt(X), rtol=1e-10)
    smooth = sharded_fn(lambda x, y: jnp.sin(x) * y, method="map")
    g = jax.jit(jax.grad(lambda x: jnp.sum(smooth(x, ys))))
    np.testing.assert_allclose(np.asarray(g(xs)), np.cos(X) * Y, rtol=1e-12)


def test_broadcast_args_are_traced_not_baked_in():
    """Broadcast arrays reach every point; a new value gives the new answer."""
    f = lambda scale, tag, x, y: {"root": scale * _point(x, y)["root"], "tag": len(tag) + 0 * x}
    for scale in (1.0, 3.0):
        out = sharded_vmap(f, (X, Y), broadcast_args=(jnp.asarray(scale), "ab"), chunk=3)
        np.testing.assert_allclose(out["root"], scale * np.sqrt(X), rtol=1e-13)
        np.testing.assert_array_equal(out["tag"], np.full(7, 2.0))


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="leading"):
        sharded_vmap(_point, (X, Y[:3]))
    with pytest.raises(ValueError, match="method"):
        sharded_vmap(_point, (X, Y), method="pmap")
    with pytest.raises(ValueError, match="chunk"):
        sharded_vmap(_point, (X, Y), chunk=0)
    with pytest.raises(TypeError, match="tuple"):
        sharded_vmap(_point, [X, Y])


def _run(code, env_extra, timeout):
    env = dict(os.environ)
    env.update(env_extra)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=timeout)


TWO_DEVICES = """
    import equinox as eqx, jax, numpy as np
    import jaxwear as jw
    from jaxwear._core.parallel import _compiled, _place, _replicate, sharded_vmap
    from jaxwear._physics.wear import build_schedule, wear_loop

    assert jax.device_count() == 2, jax.devices()
    p = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=32, steps_per_rev=36)
    sched = build_schedule(p, cfg, revolutions=1500, M=500, pad=False)  # 3 updates

    def point(p, cfg, sched, speed, clearance):
        q = p.with_values({"speed_rpm": speed, "clearance_mm": clearance})
        r = wear_loop(q, cfg, sched)
        return r.depth, r.worn_volume

    speed = np.array([148.0, 230.0, 276.0]) * 2 * np.pi / 60
    clear = np.array([0.05, 0.10, 0.15]) * 1e-3
    # lax.map per device (the method a CPU sweep uses; vmap is covered by the in-process
    # tests and compiles twice as long). 3 points, padded to 2 per device.
    fixed = (p, cfg, sched)
    depth, vol = sharded_vmap(point, (speed, clear), broadcast_args=fixed, method="map")
    single = eqx.filter_jit(point)  # unsharded reference: one point at a time, one device
    ref = [single(p, cfg, sched, s, c) for s, c in zip(speed, clear)]
    ref_depth, ref_vol = np.stack([r[0] for r in ref]), np.stack([r[1] for r in ref])
    assert depth.shape == (3, 32) and np.max(ref_depth) > 1e-7
    assert np.max(np.abs(depth - ref_depth)) <= 1e-12 * np.max(ref_depth), "depth differs"
    assert np.max(np.abs(vol - ref_vol)) <= 1e-12 * np.max(ref_vol), "volume differs"
    # The same compiled call really splits the points: one block of 2 on each device.
    call, sharding = _compiled(point, tuple(jax.devices()), "map")
    out = call(_replicate(fixed, sharding.mesh),
               (_place(np.append(speed, speed[-1]), sharding),
                _place(np.append(clear, clear[-1]), sharding)))[0]
    assert len(out.sharding.device_set) == 2
    assert sorted(s.data.shape[0] for s in out.addressable_shards) == [2, 2]
    print("OK")
"""


def test_two_devices_equal_unsharded():
    """A small wear sweep sharded over 2 (forced host) devices equals the unsharded one."""
    proc = _run(TWO_DEVICES, {"XLA_FLAGS": "--xla_force_host_platform_device_count=2",
                              "JAX_PLATFORMS": "cpu"}, timeout=240)
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stderr[-3000:]


DISTRIBUTED = """
    import sys
    import jax
    try:  # CPU collectives (the final gather) need gloo on older jax versions
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except Exception:
        pass
    port, pid = sys.argv[1], int(sys.argv[2])
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                               process_id=pid, initialization_timeout=60)
    import numpy as np
    import jaxwear as jw
    from jaxwear._core.parallel import sharded_vmap

    assert jax.process_count() == 2 and jax.device_count() == 2
    cfg = jw.ModelConfig(steps_per_rev=36)
    p = jw.preset("rig")

    def peak_load(p, cfg, speed):
        return jw.load_history(p.with_values({"speed_rpm": speed}), cfg).load[0].max()

    speed = np.linspace(100.0, 300.0, 5) * 2 * np.pi / 60
    out = sharded_vmap(peak_load, (speed,), broadcast_args=(p, cfg))
    print("RESULT", " ".join(repr(float(v)) for v in out), flush=True)
    jax.distributed.shutdown()
"""


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_jax_distributed(tmp_path):
    """Two processes on localhost, one CPU device each: both get the whole batch's result,
    equal to the single-process one."""
    script = tmp_path / "worker.py"
    script.write_text(textwrap.dedent(DISTRIBUTED))
    port = str(_free_port())
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen([sys.executable, str(script), port, str(i)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    outs = []
    try:
        for pr in procs:
            outs.append(pr.communicate(timeout=120))
    finally:
        for pr in procs:
            if pr.poll() is None:
                pr.kill()
                pr.communicate()
    import jaxwear as jw

    cfg = jw.ModelConfig(steps_per_rev=36)
    p = jw.preset("rig")
    speed = np.linspace(100.0, 300.0, 5) * 2 * np.pi / 60
    ref = [float(jax.jit(lambda s: jw.load_history(p.with_values({"speed_rpm": s}), cfg)
                         .load[0].max())(s)) for s in speed]
    for pr, (stdout, stderr) in zip(procs, outs):
        assert pr.returncode == 0, stderr[-3000:]
        line = next(ln for ln in stdout.splitlines() if ln.startswith("RESULT"))
        got = [float(v) for v in line.split()[1:]]
        np.testing.assert_allclose(got, ref, rtol=1e-12)
