"""Grounding in the loop: a trained simulator stepped tick by tick, fed collider poses and observations
(point clouds or depth images) as they arrive (`OnlineSimulator`; docs/online.md)."""
from ..sensors.camera import DepthImage
from .depth import DepthProcessing
from .simulator import Observation, OnlineSimulator, online_object

__all__ = ["DepthImage", "DepthProcessing", "Observation", "OnlineSimulator", "online_object"]
