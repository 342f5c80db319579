"""File formats of the command line, one module each: ``mesh`` (PLY and OBJ through trimesh,
XYZ, NPY), ``npz`` (streamed archives), ``glb`` (glTF 2.0 binary). BVH lives beside its reader
in ``minretarget.bvh``."""
