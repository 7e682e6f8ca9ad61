"""Analysis-by-synthesis: the joint fit of the material field and the interaction trajectory
through the differentiable simulator and renderer. No USD here."""

from .material import MaterialField
from .optimize import FitResult, FitSettings, fit
from .problem import FitProblem, LossWeights, Observations

__all__ = ["fit", "FitSettings", "FitResult", "FitProblem", "Observations", "LossWeights",
           "MaterialField"]
