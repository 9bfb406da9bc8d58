"""The demo scenes (`radfield demo-scene NAME`): tiny synthetic datasets with exact ground truth, one
registry of them. Light to import (no numpy): `radfield demo-scene --help` lists them from here.

    static   blobs, thin, checker, objects, glossy, studio   analytic shapes under one light, a
             NeRF-synthetic folder (demo/static.py; scenes.py, raytrace.py, shapes.py,
             deformations.py for --deform)
    dynamic  smoke, moving                                   every camera at every moment, a D-NeRF
             folder (demo/timelapse.py; smoke.py, moving.py)
    olat     olat, olat-glossy                               every camera under several point lights,
             one light a frame (demo/olat.py)

A family's writer module has `write(name, folder, *, train_views, test_views, size, seed, quiet,
**options) -> str`: it writes the scene into a new folder and returns the line that says what it
wrote; `options` are the family's own (Family.options). A new scene of a family is a line here
(and its recipe in the family's module); a new family is one writer module and its Family.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

from radfield.util.registry import Registry


@dataclass(frozen=True)
class Family:
    name: str                   # in messages: "the <name> scenes"
    title: str                  # what its scenes are, for the help
    writer: str                 # the module that writes its scenes (its `write`)
    options: tuple[str, ...]    # the options only its scenes take (demo-scene's flags, as keywords)


STATIC = Family("static", "Static scenes (40 + 8 views, a NeRF-synthetic folder)", "radfield.demo.static",
                ("deform", "workers"))
DYNAMIC = Family("dynamic", "Dynamic scenes (36 + 4 cameras, each at --times moments: a D-NeRF folder)",
                 "radfield.demo.timelapse", ("times", "held_out_times"))
OLAT = Family("one-light-at-a-time", "One light at a time (40 + 8 cameras, each under --lights point lights)", "radfield.demo.olat",
              ("lights",))
FAMILIES = (STATIC, DYNAMIC, OLAT)


@dataclass(frozen=True)
class DemoScene:
    name: str
    family: Family
    about: str                  # one line: what it shows

    def write(self, folder: Path, **settings) -> str:
        """Write the scene into the new folder `folder` (its family's writer); what it wrote, in one line."""
        return importlib.import_module(self.family.writer).write(self.name, Path(folder), **settings)


SCENES: Registry[DemoScene] = Registry("demo scene")
for _scene in (
    DemoScene("blobs", STATIC, "a few coloured spheres on a box: the default demo, easy"),
    DemoScene("thin", STATIC, "a wire-frame cube of sub-pixel rods"),
    DemoScene("checker", STATIC, "checkered and striped shapes: high-frequency textures"),
    DemoScene("objects", STATIC, "separate objects, a torus, thin rods; no mesh.ply, so the envelope is the visual hull"),
    DemoScene("glossy", STATIC, "glossy and matte objects with moving highlights, 100 + 20 views"),
    DemoScene("studio", STATIC, "glossy's objects rendered like a path tracer (soft shadows, moderate highlights), "
                                "100 + 20 views"),
    DemoScene("smoke", DYNAMIC, "coloured puffs that move, grow and turn"),
    DemoScene("moving", DYNAMIC, "the objects scene's shapes moving and turning"),
    DemoScene("olat", OLAT, "studio's objects under one point light at a time"),
    DemoScene("olat-glossy", OLAT, "glossy's objects: sharp highlights that move with the light, a pillar's shadow"),
):
    SCENES.register(_scene.name, _scene)
del _scene


def get(name: str) -> DemoScene:
    """The demo scene `name` (RadfieldError naming the others when there is none)."""
    return SCENES.get(name)


def names(family: Family | None = None) -> tuple[str, ...]:
    """Every demo scene's name (of `family`), in the registry's order."""
    return tuple(scene.name for scene in SCENES.values() if family is None or scene.family == family)
