"""The embedded procedural simulator: typ's default data and its ground truth.

Towns are triangle meshes built from primitives (roads with kerbs, buildings, trees, poles,
parked and moving vehicles); connected vehicles drive in lanes and scan the town with one of
three LiDAR presets (``source`` ~ OPV2V/CARLA, ``target`` ~ Waymo, ``real_cav`` ~ V2V4Real),
cast with open3d. :func:`simulate_scenario` returns :class:`typ.scene.Scene` objects and
writes nothing; :func:`cast` renders the TRUE view from any pose, which is what real data
never has.
"""
from typ.sim.raycast import TownFrame, cast, town_frame
from typ.sim.scenario import BOX_RANGE, scenario_world, sensor_pose, simulate_scenario
from typ.sim.sensor import DOMAINS, DomainSpec, SensorSpec, domain_spec, horizon_dense_elevations
from typ.sim.solids import Solids
from typ.sim.town import Town, TownStyle, build_town
from typ.sim.traffic import Traffic, simulate_traffic
from typ.sim.vehicles import VEHICLE_CLASSES

__all__ = [
    "BOX_RANGE", "DOMAINS", "DomainSpec", "SensorSpec", "Solids", "Town", "TownFrame", "TownStyle", "Traffic",
    "VEHICLE_CLASSES", "build_town", "cast", "domain_spec", "horizon_dense_elevations", "sensor_pose",
    "scenario_world", "simulate_scenario", "simulate_traffic", "town_frame",
]
