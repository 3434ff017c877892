"""Models: the Encode-Process-Decode core shared by GGNS and MGN (core.py), feature normalization
(normalization.py), training noise (training_noise.py), the lr schedule (lr_schedule.py) and the
LightningModules GGNS, GGNS+LSTM, MGN, MGN(M), the authors' MGN and the GGNS(M) ablation (simulators.py)."""
from .core import EncodeProcessDecode, GraphNetBlock, graph_features, mlp
from .normalization import Normalizer, NormalizerDict, type_key

__all__ = ["EncodeProcessDecode", "GraphNetBlock", "Normalizer", "NormalizerDict", "graph_features", "mlp", "type_key"]
