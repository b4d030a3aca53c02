"""Figures (matplotlib, imported lazily), one module per family: the paper's figures, fits,
models compared with trials, plans and Monte-Carlo studies. Each function takes a result object
and writes a PNG atomically. `plots/` sits above the packages whose results it draws, and
nothing below it imports it (docs/architecture.md); the animations (`jsphere.plots.animation`)
replay runs where a result asks for it."""

from .compare import compare_figure as compare_figure
from .fit import fit_figures as fit_figures
from .fit import worst_trial as worst_trial
from .montecarlo import figure2_study as figure2_study
from .montecarlo import montecarlo_figure as montecarlo_figure
from .paper import REPRODUCTION_FIGURES as REPRODUCTION_FIGURES
from .paper import controls_figure as controls_figure
from .paper import figure2 as figure2
from .paper import figure3 as figure3
from .paper import write_reproduction_figures as write_reproduction_figures
from .plan import plan_figure as plan_figure
