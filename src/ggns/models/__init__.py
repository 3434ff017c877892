"""Models: the Encode-Process-Decode core shared by GGNS and MGN, and feature normalization."""
from .core import EncodeProcessDecode, GraphNetBlock, graph_features, mlp
from .normalization import Normalizer, NormalizerDict, type_key

__all__ = ["EncodeProcessDecode", "GraphNetBlock", "Normalizer", "NormalizerDict", "graph_features", "mlp", "type_key"]
