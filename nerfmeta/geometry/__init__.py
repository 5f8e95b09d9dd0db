"""Surfaces: meshes from fields (marching cubes), PLY/OBJ input and output, geometry metrics against ground truth."""
