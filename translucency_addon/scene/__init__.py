"""What lights an object and what it is made of: ``materials`` (presets, mixes, per-node coefficients per
mm), ``fields`` (mixing fields), ``fresnel``, ``lights`` (lamps, the environment, eq. 3's q), ``sh``,
``environment_map`` (an HDRI to SH and a sun), ``world_nodes`` (a World's nodes as Cycles sees them).  Import
names from the module that defines them.
"""
