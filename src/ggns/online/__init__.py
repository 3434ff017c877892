"""Grounding in the loop: a trained simulator stepped tick by tick, fed collider poses and observations
(point clouds or depth images) as they arrive (`OnlineSimulator`; docs/online.md), and the registration that
corrects a blind simulator's state to each observation instead (`Registration`)."""
from ..errors import OnlineDivergence
from ..sensors.camera import DepthImage
from .depth import DepthProcessing
from .objects import Observation, online_object
from .registration import Registration
from .simulator import OnlineSimulator

__all__ = ["DepthImage", "DepthProcessing", "Observation", "OnlineDivergence", "OnlineSimulator", "Registration",
           "online_object"]
