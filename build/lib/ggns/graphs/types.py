"""Node and edge types of the simulation graph (the vocabulary shared by graph builders and
models). Edge (src, relation, dst): messages flow from src to dst and are aggregated at dst.
A graph holds only the types a scene and step actually have; models index their per-type
parameters and one-hot encodings by position in these fixed lists."""

NODE_TYPES = ("mesh", "collider", "point")

MESH_EDGE = ("mesh", "mesh_edge", "mesh")  # mesh connectivity, both directions
WORLD_EDGE = ("mesh", "world", "mesh")  # MGN world edges: mesh pairs within a radius, minus mesh edges

EDGE_TYPES = (
    MESH_EDGE,
    WORLD_EDGE,
    ("collider", "near", "mesh"),
    ("mesh", "near", "collider"),
    ("collider", "near", "collider"),
    ("point", "near", "point"),
    ("point", "near", "mesh"),
    ("mesh", "near", "point"),
    ("point", "near", "collider"),
    ("collider", "near", "point"),
)
