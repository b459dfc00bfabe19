"""Maps that outlive a session (``docs/maps.md``): the saved-map format (:mod:`.format`), the map
of a finished session (:mod:`.builder`) and relocalization of a new session into one
(:mod:`.relocalizer`). Frames and units: ``docs/conventions.md``."""

from metricslam.slam.map.format import SCHEMA_VERSION, SavedMap, load_map, save_map

__all__ = ["SCHEMA_VERSION", "SavedMap", "load_map", "save_map"]
