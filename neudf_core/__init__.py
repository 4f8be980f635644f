"""NeUDF: neural unsigned distance fields learned by volume rendering (Liu et al., CVPR 2023).

This package is the method alone: fields, renderer, sampler, trainer, meshing and metrics. It never
imports the worker or the service layers, so it can be used as a library and from the command line.
"""

__version__ = "0.1.0"
