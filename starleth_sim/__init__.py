"""StarlETH simulator: Moreau time-stepping with hard (JOR/SOR prox) and compliant contacts
(Gehring et al. 2014). The physics core imports numpy and pin only (its kernels are C); the
ROS 2 nodes live in ``starleth_sim.ros``."""
from .physics.config import PRESETS, ConfigError, PhysicsConfig, available_presets, load_preset
from .physics.diagnostics import Diagnostics
from .physics.sensors import Sensors
from .physics.simulator import ContactInfo, Simulator
from .physics.stepper import SimulationError

__all__ = ["Simulator", "ContactInfo", "Diagnostics", "PhysicsConfig", "ConfigError",
           "SimulationError", "Sensors", "load_preset", "available_presets", "PRESETS"]
