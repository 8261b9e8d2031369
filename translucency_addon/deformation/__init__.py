"""Deformation without a re-bake (Wang et al. 2010 sec. 6.4): ``attachment`` (points kept on a deforming
mesh), ``pose`` (the baked graph deformed to a pose: ``DeformationRig``), ``sky`` (its sky visibility),
``frames`` (frame after frame, the Blender side's entry point).  Import names from the module that defines them.
"""
