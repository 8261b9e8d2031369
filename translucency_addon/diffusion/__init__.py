"""Multiple scattering (Wang et al. 2010): the diffusion equation on any graph of the contract.

``graph`` (the contract every discretisation hands over), ``assembly`` (one linear system per level),
``spectral`` and ``sweeps`` (what the Chebyshev iteration needs), ``iterative`` (one level's solve),
``kernels`` (the numpy twins of the GPU kernels), ``radiance`` (J+ and the light that leaves),
``solver`` (``DiffusionSolver``, the one multi-level driver), ``interreflection`` and ``sky_visibility``
(Self-Occlusion's bounce).  Import names from the module that defines them.
"""
