"""aerialmtl: height (nDSM) and land-cover maps with MC-dropout uncertainty from aerial orthophotos.

The method is the multi-task D3-Net of Carvalho et al., "Multi-task learning of height and semantics
from aerial images", IEEE GRSL 2019.
"""

__version__ = "0.1.0"
