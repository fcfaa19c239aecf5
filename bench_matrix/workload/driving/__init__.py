"""Procedural synthetic driving workload: circuits, front-camera renderer, expert labels, data set."""

from .circuit import Circuit
from .dataset import DrivingData, generate
from .expert import ExpertController
from .render import Camera, Lighting, render

__all__ = ["Camera", "Circuit", "DrivingData", "ExpertController", "Lighting", "generate", "render"]
