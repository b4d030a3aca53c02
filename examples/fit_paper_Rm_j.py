"""The paper's unknown R_m and j from its two reported numbers, with the fit machinery.

The paper gives Omega_1 = 0.864 1/s after the acceleration gait (5.1) and 0.852 1/s after the
turn (5.6), but neither R_m nor j. `jsphere.FreeParams` maps an unconstrained vector to R_m, j
(both log-transformed: positive), `jsphere.least_squares` (Levenberg-Marquardt, Jacobian by
reverse-mode autodiff through diffrax) solves the two equations, and the covariance follows
from the rounding of the reported numbers (uniform within +-0.0005: sd 0.0005/sqrt(3)).

    python examples/fit_paper_Rm_j.py
"""

import math

import jax.numpy as jnp
import numpy as np

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

REPORTED = np.array([0.864, 0.852])
SD = 0.0005 / math.sqrt(3.0)  # rounding to three decimals

start = jsphere.RobotParams.paper(R_m=0.025, j=1.0e-4)  # deliberately off
free = jsphere.FreeParams(start, "R_m,j")
accel = [jsphere.acceleration(), jsphere.braking()]
turned = [jsphere.acceleration(), jsphere.turn(), jsphere.braking(phi=np.pi / 4)]
# the sample at the end of the first gait (acceleration) and of the second (turn): static indices
i_acc = int(np.nonzero(np.asarray(jsphere.simulate_gaits(start, accel).segment) == 0)[0][-1])
i_turn = int(np.nonzero(np.asarray(jsphere.simulate_gaits(start, turned, reset=[True, None]).segment) == 1)[0][-1])


def residuals(theta):
    p = free.to_params(theta)
    a = jsphere.simulate_gaits(p, accel)
    t = jsphere.simulate_gaits(p, turned, reset=[True, None])
    return (jnp.stack([a.Omega[i_acc, 1], t.Omega[i_turn, 1]]) - REPORTED) / SD


sol = jsphere.least_squares(residuals, free.theta0)
values = np.asarray(free.physical(jnp.asarray(sol.x)))
cov = free.physical_covariance(sol.x, sol.covariance)
se = np.sqrt(np.diag(cov))
corr = cov[0, 1] / (se[0] * se[1])
print(f"Levenberg-Marquardt: {sol.iterations} iterations, residual |r| = {math.sqrt(2 * sol.cost):.2e} (in SD units)")
print(f"R_m = {values[0] * 1e3:.4f} +- {se[0] * 1e3:.4f} mm   (docs/model.md: 27.0146 mm)")
print(f"j   = {values[1] * 1e4:.4f} +- {se[1] * 1e4:.4f} e-4 kg m^2   (docs/model.md: 2.7395e-4)")
print(f"correlation(R_m, j) = {corr:+.3f}")
assert abs(values[0] - jsphere.model.params.PAPER_R_M) < 1e-7 and abs(values[1] - jsphere.model.params.PAPER_J) < 1e-8
