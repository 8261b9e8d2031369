"""The QuadGraph bake (Wang et al. 2010 sec. 4.1, 5.1): ``tetra`` (fTetWild, C2/C3 splits, refinement),
``levels`` (one QuadGraph level from a tet mesh: ``GraphLevel``), ``bake`` (mesh in, multi-resolution graph
out: ``bake_mesh``, ``Bake``, ``BakeSettings``).  Import names from the module that defines them.
"""
