"""Meshes for the rasteriser tests."""


def colored(mesh, rgb):
    """``mesh`` (a trimesh) with every face the colour ``rgb`` (0–255), opaque."""
    mesh.visual.face_colors = (*rgb, 255)
    return mesh
