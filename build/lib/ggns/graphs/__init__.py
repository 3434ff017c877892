"""Graphs: the system state of one step (mesh, collider, optional point cloud) as HeteroData."""
