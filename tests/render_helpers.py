"""Helpers shared by the render tests (tests/test_render_*.py)."""

import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
