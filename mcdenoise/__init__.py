"""mcdenoise: neural denoising of Monte Carlo renderings.

Pipeline, one sub-package per stage: render -> data -> ops -> models -> train -> eval -> cli.
"""

__version__ = "0.1.0"
