"""Procedural, georeferenced synthetic scenes for running, testing and pretraining the pipeline offline.

One generator in two styles. :func:`synthesize` writes an RGB orthophoto, DSM, DTM, nDSM and land-cover labels of
a random **town** (terrain, roads, houses with gable roofs, commercial blocks, parks with ponds, forests, fields;
the demo's scenes; :mod:`~aerialmtl.data.synth.scene`, :mod:`~aerialmtl.data.synth.render`) in which height is
visible in the image through sun-direction cast shadows and roof shading. :func:`sample_city` draws a synthetic
**city** patch in memory (towers, halls with ground-like roofs, stadium stands, the lean of a non-true orthophoto,
per-scene sun and sensor style; :mod:`~aerialmtl.data.synth.city`), the fast scene source for pretraining;
:func:`synthesize_city` writes one.

Both styles are layouts over the same primitives, each with one owner: the pixel grid, street frame and
"highest surface wins" rule (:mod:`~aerialmtl.data.synth.canvas`), class codes, colours, jitter and texture
(:mod:`~aerialmtl.data.synth.materials`), street grids (:mod:`~aerialmtl.data.synth.streets`), roof and crown
shapes (:mod:`~aerialmtl.data.synth.shapes`), smooth noise (:mod:`~aerialmtl.data.synth.noise`) and the sun, its
cast shadows and the sky light (:mod:`~aerialmtl.data.synth.shading`).
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
