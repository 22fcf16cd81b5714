"""Building graphs: the map file format, validation and the arrays the particle filter walks on.

``load_graph(path)`` / ``save_graph(g, path)`` read and write format ``indoor_loc.graph`` v1
(:mod:`indoor_loc.graph.io`); :class:`BuildingGraph` holds ``node_xyz (M, 3)``,
``link_nodes (L, 2)``, ``link_len (L,)`` and the CSR adjacency (:mod:`indoor_loc.graph.model`).
"""
from indoor_loc.graph.io import FORMAT_NAME, FORMAT_VERSION, graph_from_dict, graph_to_dict, load_graph, save_graph
from indoor_loc.graph.model import BuildingGraph, Floor, build_graph

__all__ = ["BuildingGraph", "Floor", "build_graph", "load_graph", "save_graph", "graph_from_dict",
           "graph_to_dict", "FORMAT_NAME", "FORMAT_VERSION"]
