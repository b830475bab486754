"""Networks built from bench.nn layers (floor 2). The proposed model is SRDNet."""
from .srd import SRDNet

__all__ = ["SRDNet"]
