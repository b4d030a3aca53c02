"""Verner's "most efficient" 7(6) Runge-Kutta pair as a diffrax solver, for the
work-precision benchmark (`work_precision.py`): it runs in jsphere's batch loop as any
user-defined explicit method does (`jsphere.solve.batched.method.tableau`).

The coefficients are Verner's (J. H. Verner, "Numerically optimal Runge-Kutta pairs with
interpolants", Numer. Algorithms 53 (2010) 383-396; the pair RKV76.IIa "Efficient",
published at https://www.sfu.ca/~jverner/ as RKV76.IIa.Efficient.00001675585.081206), to the
digits published there. The pair has 10 stages, the solution of order 7 from stages 1-9 and
the embedded one of order 6 from stages 1-7 and 10. Here an 11th stage at `c = 1` with the
solution's weights is appended, the rates at the step's end, so that the tableau is first
same as last: each step then costs 10 evaluations of the field, the first stage of the next
step included, as Verner's pair does when its rates at the end are reused.

Dense output: Verner's interpolant of order 7 needs six more stages, which diffrax's
interpolation classes cannot evaluate, so save times inside a step use a cubic Hermite
interpolant (diffrax's `ThirdOrderHermitePolynomialInterpolation`). The benchmark reads the
state at the end time only, which is the step's solution itself, not an interpolated value.
This solver is for measurement, not for use.
"""

from __future__ import annotations

from typing import ClassVar

import diffrax
import numpy as np
from diffrax import ButcherTableau

# fmt: off
_c = np.array([0.0, 0.005, 0.1088888888888888888888888888888888888889, 0.1633333333333333333333333333333333333333,
    0.4555, 0.6095094489978381317087004421486024949638, 0.884, 0.925, 1.0, 1.0])
_a = np.zeros((10, 10))
_a[1, :1] = [0.005]
_a[2, :2] = [-1.076790123456790123456790123456790123457, 1.185679012345679012345679012345679012346]
_a[3, :3] = [0.04083333333333333333333333333333333333333, 0.0, 0.1225]
_a[4, :4] = [0.6389139236255726780508121615993336109954, 0.0, -2.455672638223656809662640566430653894211,
    2.272258714598084131611828404831320283215]
_a[5, :5] = [-2.661577375018757131119259297861818119279, 0.0, 10.80451388645613769565396655365532838482,
    -8.353914657396199411968048547819291691541, 0.8204875949566569791420417341743839209619]
_a[6, :6] = [6.067741434696770992718360183877276714679, 0.0, -24.71127363591108579734203485290746001803,
    20.42751793078889394045773111748346612697, -1.906157978816647150624096784352757010879,
    1.006172249242068014790040335899474187268]
_a[7, :7] = [12.05467007625320299509109452892778311648, 0.0, -49.75478495046898932807257615331444758322,
    41.14288863860467663259698416710157354209, -4.461760149974004185641911603484815375051,
    2.042334822239174959821717077708608543738, -0.09834843665406107379530801693870224403537]
_a[8, :8] = [10.13814652288180787641845141981689030769, 0.0, -42.64113603171750214622846006736635730625,
    35.76384003992257007135021178023160054034, -4.348022840392907653340370296908245943710,
    2.009862268377035895441943593011827554771, 0.3487490460338272405953822853053145879140,
    -0.2714390051048312842371587140910297407572]
_a[9, :9] = [-45.03007203429867712435322405073769635151, 0.0, 187.3272437654588840752418206154201997384,
    -154.0288236935018690596728621034510402582, 18.56465306347536233859492332958439136765,
    -7.141809679295078854925420496823551192821, 1.308808578161378625114762706007696696508, 0.0, 0.0]
_b = np.array([0.04715561848627222170431765108838175679569, 0.0, 0.0, 0.2575056429843415189596436101037687580986,
    0.2621665397741262047713863095764527711129, 0.1521609265673855740323133199165117535523,
    0.4939969170032484246907175893227876844296, -0.2943031171403250441557244744092703429139,
    0.08131747232495109999734599440136761892478, 0.0])
_bh = np.array([0.04460860660634117628731817597479197781432, 0.0, 0.0, 0.2671640378571372680509102260943837899738,
    0.2201018300177293019979715776650753096323, 0.2188431703143156830983120833512893824578,
    0.2289871705411202883378173889763552365362, 0.0, 0.0, 0.02029518466335628222767054793810430358554])
# fmt: on


def _fsal_tableau() -> ButcherTableau:
    """The pair's tableau with the 11th stage appended (module docstring)."""
    s = 11
    a = np.zeros((s, s))
    a[:10, :10] = _a
    a[10, :10] = _b
    b_sol = np.concatenate([_b, [0.0]])
    b_error = np.concatenate([_b - _bh, [0.0]])
    c = np.concatenate([_c, [1.0]])
    return ButcherTableau(c=c[1:], b_sol=b_sol, b_error=b_error, a_lower=tuple(a[i, :i] for i in range(1, s)))


class Vern7(diffrax.AbstractERK):
    """Verner's 7(6) "most efficient" pair (module docstring): 7th order, 10 field
    evaluations per step, cubic Hermite dense output."""

    tableau: ClassVar[ButcherTableau] = _fsal_tableau()
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 7
