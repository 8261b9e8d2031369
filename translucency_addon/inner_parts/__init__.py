"""Cavities and several media (Mochida et al.): ``composite`` (an outer mesh and inner parts with roles),
``cavity`` (the cavity exchange in the diffusion solve), ``bake`` (the composite bake: QuadGraph with cavities
carved, exchange, labels, Voxel Number Map).  Import names from the module that defines them.
"""
