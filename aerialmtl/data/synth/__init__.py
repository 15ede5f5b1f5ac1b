"""Procedural, georeferenced synthetic towns for running and testing the whole pipeline offline.

:func:`synthesize` writes an RGB orthophoto, DSM, DTM, nDSM and land-cover labels of a random town
(terrain, roads, houses with gable roofs, commercial blocks, parks with ponds, forests, fields) in
which height is visible in the image through sun-direction cast shadows and roof shading.

:func:`sample_city` draws a synthetic city patch in memory (towers, halls with ground-like roofs, stadium
stands, the lean of a non-true orthophoto, per-scene sun and sensor style; :mod:`aerialmtl.data.synth.city`),
the fast scene source for pretraining.
"""

from aerialmtl.data.synth.city import CityPatch, sample_city
from aerialmtl.data.synth.generate import MIN_SIZE, SYNTH_VERSION, CityResult, SynthResult, synthesize, synthesize_city
from aerialmtl.data.synth.render import AMBIENT, render_ortho
from aerialmtl.data.synth.scene import build_scene
from aerialmtl.data.synth.scene_parts import Scene
from aerialmtl.data.synth.shading import cast_shadows, hillshade, sun_vector
from aerialmtl.data.synth.style import CityStyle, Imaging
from aerialmtl.data.synth.textures import TexturePool

__all__ = [
    "AMBIENT",
    "CityPatch",
    "CityResult",
    "CityStyle",
    "Imaging",
    "TexturePool",
    "MIN_SIZE",
    "SYNTH_VERSION",
    "Scene",
    "SynthResult",
    "build_scene",
    "cast_shadows",
    "hillshade",
    "render_ortho",
    "sample_city",
    "sun_vector",
    "synthesize",
    "synthesize_city",
]
