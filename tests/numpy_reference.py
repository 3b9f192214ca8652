"""Independent float64 NumPy transcriptions of the paper's equations and of a textbook GP, written from the paper and
the textbook (not from cpgjax)."""

import numpy as np

PHI = np.array([[0, np.pi, np.pi, 0], [-np.pi, 0, 0, -np.pi], [-np.pi, 0, 0, -np.pi], [0, np.pi, np.pi, 0]])


def hopf_derivatives(
    r, theta, mu, omega_swing, omega_stance, sigma_n, normal_force, tegotae=True, alpha=50.0, squared_mu=True
):
    """Eqs. (1)-(3) and (6), loop by loop."""
    dr = np.zeros(4)
    dtheta = np.zeros(4)
    for i in range(4):
        target = mu**2 if squared_mu else mu
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
    g_c, g_p, w_sw, w_st, mu, _, _, sigma = params  # x_f, x_h shape the foot path, not the oscillator
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


# ---- a dense float64 GP (Rasmussen & Williams, Alg. 2.1) with cpgjax.gp's model -----------------


def ref_matern52(distance):
    return (1 + np.sqrt(5) * distance + 5 / 3 * distance**2) * np.exp(-np.sqrt(5) * distance)


def ref_kernel(a, b, lengthscales, outputscale, active, context_dims):
    d = a.shape[1]
    blocks = [range(d - context_dims), range(d - context_dims, d)]
    k = outputscale * np.ones((len(a), len(b)))
    for block in blocks:
        cols = [c for c in block if active[c]]
        diff = (a[:, None, cols] - b[None, :, cols]) / lengthscales[cols]
        k = k * ref_matern52(np.sqrt(np.sum(diff**2, axis=-1)))
    return k


class RefGP:
    """float64 GP with the same model: standardized y, constant mean, relative jitter."""

    def __init__(self, params, inputs, targets, active, context_dims, jitter_ratio):
        self.ls = np.exp(np.asarray(params.log_lengthscales, np.float64))
        self.s2 = float(np.exp(params.log_outputscale))
        self.noise = float(np.exp(params.log_noise))
        self.mean = float(params.mean)
        self.active, self.context_dims = np.asarray(active), context_dims
        self.x = np.asarray(inputs, np.float64)
        y = np.asarray(targets, np.float64)
        self.y_mean = y.mean()
        self.y_std = y.std(ddof=1) if len(y) > 1 and y.std(ddof=1) >= 1e-8 else 1.0
        self.residual = (y - self.y_mean) / self.y_std - self.mean
        n = len(y)
        self.kernel = self.k(self.x, self.x) + (jitter_ratio * self.s2 + self.noise) * np.eye(n)

    def k(self, a, b):
        return ref_kernel(a, b, self.ls, self.s2, self.active, self.context_dims)

    def log_marginal_likelihood(self):
        _, logdet = np.linalg.slogdet(self.kernel)
        n = len(self.residual)
        quad = self.residual @ np.linalg.solve(self.kernel, self.residual)
        return -0.5 * quad - 0.5 * logdet - 0.5 * n * np.log(2 * np.pi)

    def predict(self, queries):
        queries = np.asarray(queries, np.float64)
        cross = self.k(queries, self.x)
        mean_z = self.mean + cross @ np.linalg.solve(self.kernel, self.residual)
        var_z = self.s2 - np.einsum("ij,ji->i", cross, np.linalg.solve(self.kernel, cross.T))
        return self.y_mean + self.y_std * mean_z, self.y_std**2 * var_z
