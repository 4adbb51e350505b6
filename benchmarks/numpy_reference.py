"""Independent plain-NumPy reference of the crank-slider wear model (design.md §1, §3, §4).

Written "as the paper describes it": Python loops over wear updates and over the steps of a
revolution, NumPy vectorisation over the bore nodes only. No JAX, so it shares no code with
`jaxwear` and can serve as an outside check of it (and as the slow baseline in benchmarks).

    /work/venv/bin/python benchmarks/numpy_reference.py
"""

import math
import time

import numpy as np

# Rig preset: Table 1 (mechanism) and Table 3 (joint), SI units.
L1, L2 = 0.070, 0.200
M2, M3 = 1.0943, 5.0
G_ACC = 9.81
R_B, WIDTH, LAYER = 7.5e-3, 0.028, 0.5e-3
E_PTFE, NU_PTFE = 0.5e9, 0.3
E_W = (1 - NU_PTFE) * E_PTFE / ((1 + NU_PTFE) * (1 - 2 * NU_PTFE))  # eq 15


def kinematics(phi1, omega, gamma, xi, l1=L1):
    """Eqs 3-7 with constant crank speed and a stationary clearance link (γ̇ = γ̈ = 0).

    Scalars or NumPy arrays (element-wise); `l1` the crank length [m] (Table 1 by default)."""
    s1, c1 = np.sin(phi1), np.cos(phi1)
    phi2 = np.arcsin((l1 * s1 + xi * np.sin(gamma)) / L2)  # eq 3
    s2, c2 = np.sin(phi2), np.cos(phi2)
    phi2_d = l1 * omega * c1 / (L2 * c2)  # eq 4
    phi2_dd = (-l1 * omega**2 * s1 + L2 * phi2_d**2 * s2) / (L2 * c2)  # eq 5
    xs = l1 * c1 + L2 * c2 + xi * np.cos(gamma)  # eq 1
    xs_dd = -l1 * omega**2 * c1 - L2 * phi2_dd * s2 - L2 * phi2_d**2 * c2  # eq 7
    return phi2, phi2_d, phi2_dd, xs, xs_dd


def pin_force(phi1, omega, phi2, phi2_d, phi2_dd, xs, xs_dd, spring, x0, l1=L1):
    """F_C, the force of the slider's pin on the coupler (eqs 8-10 as fixed in design.md §1).

    Scalars or NumPy arrays (element-wise)."""
    fcx = -spring * (xs - x0) - M3 * xs_dd  # slider, x: m3 ẍs = F_s - F_Cx
    s2, c2 = np.sin(phi2), np.cos(phi2)
    r_db = (L2 * c2, -L2 * s2)  # D - B; D = B + L2 (cos Φ2, -sin Φ2)
    r_gb = (0.5 * r_db[0], 0.5 * r_db[1])  # uniform bar: G at the midpoint
    # a_G = a_B + (L2/2) d²/dt² (cos Φ2, -sin Φ2), crank at constant speed
    a_gx = -l1 * omega**2 * np.cos(phi1) + 0.5 * L2 * (-s2 * phi2_dd - c2 * phi2_d**2)
    a_gy = -l1 * omega**2 * np.sin(phi1) + 0.5 * L2 * (-c2 * phi2_dd + s2 * phi2_d**2)
    qx, qy = -M2 * a_gx, -M2 * a_gy - M2 * G_ACC  # inertia + weight, applied at G
    i_g = M2 * L2**2 / 12.0
    psi_dd = -phi2_dd  # coupler direction angle ψ = -Φ2
    # Moments about B (the crank's force on the coupler acts at B, so it drops out):
    # (r_db x F_C) + (r_gb x Q) - I_G ψ̈ = 0, with a x b = ax by - ay bx; solve for F_Cy.
    m_q = r_gb[0] * qy - r_gb[1] * qx
    fcy = (r_db[1] * fcx - m_q + i_g * psi_dd) / r_db[0]
    return fcx, fcy


def load_history(speed_rpm, steps, clearance, spring, scla_passes, gamma0, x0=None, l1=L1):
    """SCLA (paper §1.2): γ frozen per step, forces, γ <- atan2(F_Cy, F_Cx), repeat.

    `x0` the spring's free position (default L2 - l1, design.md §1), `l1` the crank length.
    Returns F (steps, 2), θ_W (steps,) in the bushing (coupler) frame, Φ̇2 (steps,) and T.
    """
    x0 = L2 - l1 if x0 is None else x0
    omega = 2 * math.pi * speed_rpm / 60.0
    gamma = np.full(steps, float(gamma0))
    force = np.zeros((steps, 2))
    phi2 = np.zeros(steps)
    phi2_d = np.zeros(steps)
    for _ in range(scla_passes):
        for i in range(steps):
            phi1 = 2 * math.pi * i / steps
            kin = kinematics(phi1, omega, gamma[i], clearance, l1)
            phi2[i], phi2_d[i] = kin[0], kin[1]
            force[i] = pin_force(phi1, omega, *kin, spring, x0, l1)
        gamma = np.arctan2(force[:, 1], force[:, 0])  # eq 11, quadrant fixed
    # Bushing in the coupler eye: θ_W = γ - ψ = γ + Φ2 (Φ2 from the last pass's kinematics).
    theta_w = np.arctan2(np.sin(gamma + phi2), np.cos(gamma + phi2))  # wrapped to (-π, π]
    return force, theta_w, phi2_d, 2 * math.pi / omega


def _solve_1d(cosb, gap, ka, w_mag):
    """s ≥ 0 with Σ kA max(s cosβ - g, 0) cosβ = |W|: convex, increasing, piecewise linear.

    Newton from the first-contact point s0 (where f < 0) overshoots once, then decreases
    monotonically to the root: no safeguard needed.
    """
    pos = cosb > 0
    s = np.min(gap[pos] / cosb[pos])
    for _ in range(200):
        d = s * cosb - gap
        act = d >= 0
        f = np.sum(ka[act] * d[act] * cosb[act]) - w_mag
        slope = np.sum(ka[act] * cosb[act] ** 2)
        if abs(f) <= 1e-13 * w_mag:
            break
        s -= f / slope
    return s


def contact_unsymmetric(normals, gap, k, area, w_vec, tol=1e-10):
    """Pressures p_j from Σ_j p_j A_j n_j = W (design.md §3), e a free 2-vector.

    The residual is the gradient of the convex potential Π(e) = Σ ½ kA max(e·n - g, 0)² - W·e,
    so a (semi-smooth) Newton step with backtracking on Π converges from the 1-D solution
    along the load (a good start, exact for an unworn bore).
    """
    w_mag = math.hypot(w_vec[0], w_vec[1])
    if w_mag == 0.0:
        return np.zeros_like(gap)
    ka = k * area
    u = w_vec / w_mag
    e = _solve_1d(normals @ u, gap, ka, w_mag) * u

    def potential(e):
        d = np.maximum(normals @ e - gap, 0.0)
        return 0.5 * np.sum(ka * d * d) - w_vec @ e

    def gradient(e):
        d = normals @ e - gap
        act = d > 0
        kn = ka[act, None] * normals[act]
        return kn.T @ d[act] - w_vec, kn.T @ normals[act]

    grad, hess = gradient(e)
    for _ in range(100):
        if math.hypot(grad[0], grad[1]) < tol * w_mag:
            break
        # Tiny shift relative to the active stiffness: one active node gives a rank-1 Hessian.
        step = -np.linalg.solve(hess + 1e-12 * np.trace(hess) * np.eye(2), grad)
        pi0, t = potential(e), 1.0
        while t > 1e-10:
            new_grad, new_hess = gradient(e + t * step)
            # Armijo on Π; near the root Π is flat to round-off, so a step that lands within
            # tolerance is accepted as it stands.
            if (potential(e + t * step) <= pi0 + 1e-4 * t * (grad @ step)
                    or math.hypot(new_grad[0], new_grad[1]) < tol * w_mag):
                break
            t *= 0.5
        e, grad, hess = e + t * step, new_grad, new_hess
    else:
        raise RuntimeError("unsymmetric contact: Newton did not converge")
    return k * np.maximum(normals @ e - gap, 0.0)  # eq 14


def periodic_interp(values, theta):
    """Linear interpolation on the periodic node grid θ_j = 2πj/N."""
    n = len(values)
    x = (theta % (2 * math.pi)) / (2 * math.pi) * n
    j = int(math.floor(x)) % n
    f = x - math.floor(x)
    return (1 - f) * values[j] + f * values[(j + 1) % n]


def simulate_rig(speed_rpm=276.0, revolutions=10000, M=100, nodes=360, steps=360,
                 clearance_m=0.05e-3, K_d=1e-13, spring=1009.4, contact="unsymmetric",
                 scla_passes=2, gamma0=0.0, h_at_load="interp"):
    """Wear of the rig's coupler bushing after `revolutions` crank turns (SI units).

    `h_at_load` ("interp" | "nearest") picks how the symmetric model reads h(θ_W).
    """
    force, theta_w, phi2_d, period = load_history(
        speed_rpm, steps, clearance_m, spring, scla_passes, gamma0)
    w_mag = np.hypot(force[:, 0], force[:, 1])
    r_p = R_B - clearance_m  # the clearance changes the pin, not the bore
    ds = r_p * np.abs(phi2_d) * period / steps  # relative rotation is the coupler's, Φ̇2
    theta = 2 * math.pi * np.arange(nodes) / nodes
    normals = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    area = R_B * (2 * math.pi / nodes) * WIDTH
    h = np.zeros(nodes)
    archard_volume = 0.0
    # Eq 23: updates of M revolutions (profile frozen), then the remainder.
    blocks = [M] * (revolutions // M) + ([revolutions % M] if revolutions % M else [])
    done = 0
    for block in blocks:
        dh = np.zeros(nodes)
        load_ds = 0.0  # Σ_i (Σ_j p_ij A_j) dS_i over one revolution
        k_nodes = E_W / (LAYER - h)  # eq 14 with the worn, thinner layer (frozen in a block)
        for i in range(steps):
            if contact == "unsymmetric":
                w_vec = w_mag[i] * np.array([math.cos(theta_w[i]), math.sin(theta_w[i])])
                p = contact_unsymmetric(normals, clearance_m + h, k_nodes, area, w_vec)
            elif contact == "symmetric":
                # Traditional model: a circle through the loaded point of the worn bore.
                if h_at_load == "interp":
                    h_w = periodic_interp(h, theta_w[i])
                else:
                    h_w = h[int(round(theta_w[i] % (2 * math.pi) / (2 * math.pi) * nodes)) % nodes]
                gap, k = clearance_m + h_w, E_W / (LAYER - h_w)
                cosb = np.cos(theta - theta_w[i])
                if w_mag[i] == 0.0:
                    p = np.zeros(nodes)
                else:
                    s = _solve_1d(cosb, np.full(nodes, gap), np.full(nodes, k * area), w_mag[i])
                    p = k * np.maximum(s * cosb - gap, 0.0)
            else:
                raise ValueError(f"contact must be 'unsymmetric' or 'symmetric', got {contact!r}")
            dh += K_d * p * ds[i]  # eq 21
            load_ds += np.sum(p) * area * ds[i]
        h = h + block * dh  # eq 23
        archard_volume += K_d * block * load_ds
        done += block
        if np.any(h >= LAYER):
            raise RuntimeError(f"layer worn through at revolution {done}")
    return {"h": h, "theta_W": theta_w, "F": force, "dS": ds,
            "volume_m3": float(np.sum(h) * area), "archard_volume_m3": archard_volume}


def _zone_peak(h_um, lo_deg, hi_deg):
    """(depth, angle) of the deepest node with angle in [lo, hi) degrees, wrapping at 360."""
    deg = np.arange(len(h_um)) * 360.0 / len(h_um)
    mask = ((deg - lo_deg) % 360.0) < ((hi_deg - lo_deg) % 360.0)
    j = np.flatnonzero(mask)[np.argmax(h_um[mask])]
    return h_um[j], deg[j]


if __name__ == "__main__":
    # design.md §8 test vectors (an independent implementation of the same page).
    force, theta_w, phi2_d, period = load_history(276.0, 360, 0.05e-3, 1009.4, 2, 0.0)
    table = {0: (253.343, 5.366, 1.214), 45: (95.810, -32.480, -4.403),
             90: (-167.107, 60.136, -179.299), 270: (-167.102, -49.396, 175.976)}
    print("step   F_Cx (N)   F_Cy (N)  θ_W (deg)   | §8: F_Cx, F_Cy, θ_W")
    for i, ref in table.items():
        print(f"{i:4d} {force[i, 0]:10.3f} {force[i, 1]:10.3f} {math.degrees(theta_w[i]):10.3f}"
              f"   | {ref[0]:.3f}, {ref[1]:.3f}, {ref[2]:.3f}")
    sliding = np.sum((R_B - 0.05e-3) * np.abs(phi2_d) * period / 360) * 1e3
    print(f"sliding per revolution {sliding:.3f} mm (§8: 10.655)")

    t0 = time.perf_counter()
    out = simulate_rig()
    wall = time.perf_counter() - t0
    h_um = out["h"] * 1e6
    peak, at = _zone_peak(h_um, 90.0, 270.0)
    peak0, at0 = _zone_peak(h_um, 270.0, 90.0)
    print(f"unsymmetric: peak {peak:.3f} um at {at:.0f} deg (§8: 8.039 at 179), "
          f"second zone {peak0:.3f} um at {at0:.0f} deg (§8: 6.217 near 0)")
    print(f"  volume {out['volume_m3'] * 1e9:.4f} mm^3 (§8: 2.034), Archard volume "
          f"{out['archard_volume_m3'] * 1e9:.4f} mm^3; wall time {wall:.1f} s (10000 rev, M=100)")
    for how in ("interp", "nearest"):
        sym = simulate_rig(contact="symmetric", h_at_load=how)
        peak, at = _zone_peak(sym["h"] * 1e6, 90.0, 270.0)
        print(f"symmetric ({how} h(θ_W)): peak {peak:.3f} um at {at:.0f} deg (§8: 15.59 at 179), "
              f"volume {sym['volume_m3'] * 1e9:.4f} mm^3")
