"""What a fitted model lacks: the projected score test over candidate effects and
non-physical causes (docs/diagnose.md). No USD, no CLI."""

from .core import (CANDIDATES, CONFUSABLE, FIXES, PHYSICAL, BaseState, CandidateResult, DiagnoseSettings, Diagnosis,
                   conclude, diagnose_problem, realised_gauss_newton)
from .evidence import describe
from .residual import ImageResidual, loss
from .score import block_signflip, gauss_newton_drop, joint_step, predicted_drop, project_out

__all__ = ["CANDIDATES", "CONFUSABLE", "FIXES", "PHYSICAL", "BaseState", "CandidateResult", "DiagnoseSettings",
           "Diagnosis", "conclude", "diagnose_problem", "realised_gauss_newton", "describe", "ImageResidual", "loss",
           "block_signflip", "gauss_newton_drop", "joint_step", "predicted_drop", "project_out"]
