"""Triangle meshes as arrays: ``meshio`` (OBJ, validation, normals), ``raycast`` (a BVH in numpy: rays,
closest points, inside tests), ``primitives`` (procedural test meshes).  Import names from the module that
defines them.
"""
