"""Landmark maps: the schema (see SCHEMA.md), the loader and the bundled maps."""

from signpose.maps.loader import MapSign, SignMap, bundled_map_path, load_map, write_map

__all__ = ["MapSign", "SignMap", "bundled_map_path", "load_map", "write_map"]
