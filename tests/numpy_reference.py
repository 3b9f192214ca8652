"""Independent float64 NumPy transcriptions of the paper's equations, written from the paper (not from cpgjax)."""

import numpy as np

PHI = np.array([[0, np.pi, np.pi, 0], [-np.pi, 0, 0, -np.pi], [-np.pi, 0, 0, -np.pi], [0, np.pi, np.pi, 0]])


def hopf_derivatives(r, theta, mu, omega_swing, omega_stance, sigma_n, normal_force, tegotae=True,
                     alpha=50.0, squared_mu=True):
    """Eqs. (1)-(3) and (6), loop by loop."""
    dr = np.zeros(4)
    dtheta = np.zeros(4)
    for i in range(4):
        target = mu ** 2 if squared_mu else mu
        dr[i] = alpha * (target - r[i] ** 2) * r[i]
        omega = omega_swing if np.sin(theta[i]) > 0 else omega_stance
        coupling = 0.0
        for j in range(4):
            coupling += r[j] * 1.0 * np.sin(theta[j] - theta[i] - PHI[i, j])
        dtheta[i] = omega + coupling
        if tegotae:
            dtheta[i] -= sigma_n * normal_force[i] * np.cos(theta[i])
    return dr, dtheta


def integrate(r, theta, params, normal_force, steps, dt=1e-3, tegotae=True, squared_mu=True):
    """Forward Euler, θ wrapped to [0, 2π) each step."""
    g_c, g_p, w_sw, w_st, mu, xf, xh, sigma = params
    r, theta = np.array(r, float), np.array(theta, float)
    for _ in range(steps):
        dr, dth = hopf_derivatives(r, theta, mu, w_sw, w_st, sigma, normal_force, tegotae, squared_mu=squared_mu)
        r = r + dt * dr
        theta = np.mod(theta + dt * dth, 2 * np.pi)
    return r, theta


def foot_position(r, theta, params, d_step=0.05, h=0.30, foot_y=0.08):
    """Eqs. (4)-(5) in the leg frame; legs FR, FL, RR, RL."""
    g_c, g_p, _, _, _, x_front, x_hind, _ = params
    out = np.zeros((4, 3))
    for i in range(4):
        x_off = x_front if i < 2 else x_hind
        out[i, 0] = x_off - d_step * r[i] * np.cos(theta[i])
        gain = g_c if np.sin(theta[i]) > 0 else g_p
        out[i, 2] = -h + gain * np.sin(theta[i])
        out[i, 1] = (1 if i in (1, 3) else -1) * foot_y
    return out
