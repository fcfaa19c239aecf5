"""Procedural synthetic driving workload: circuits, front-camera renderer, expert labels, data set."""

from .bends import BEND_CLASSES, bend_classes
from .circuit import Circuit
from .dataset import DrivingData, generate
from .expert import ExpertController
from .render import Camera, Lighting, render

__all__ = ["BEND_CLASSES", "Camera", "Circuit", "DrivingData", "ExpertController", "Lighting", "bend_classes",
           "generate", "render"]
