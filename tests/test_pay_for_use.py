"""A scene compiles and launches only the parts it uses (GUIDE principle 1)."""

import json
import subprocess
import sys

import pytest

PROBE = """
import json, sys
from warp_cloth.util import quiet_warp; quiet_warp()
from warp_cloth.scenes import build_scene
kw = json.loads(sys.argv[1])
build_scene(kw.pop("scene"), frames=3, res=4, **kw).run(None, quiet=True)
try:
    import warp._src.context as ctx
except ImportError:
    import warp.context as ctx
loaded = sorted(name for name, m in ctx.user_modules.items()
                if name.startswith("warp_cloth") and m.execs)
print(json.dumps(loaded))
"""


def loaded_modules(**kw):
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(kw)], capture_output=True,
                         text=True, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_plain_hanging_cloth_compiles_only_springs_and_explicit():
    """Self-collision off (it is on by default in the built-in scenes): nothing of the
    collision layer is compiled."""
    mods = loaded_modules(scene="hanging", solver="explicit", self_collision=False)
    assert mods == {"warp_cloth.diagnostics", "warp_cloth.solvers.common",
                    "warp_cloth.forces.springs", "warp_cloth.solvers.explicit"}


def test_hanging_cloth_with_self_collision_compiles_no_obstacle_contact():
    """The default hanging scene (self-collision on, no obstacle) compiles the self-collision
    layer but none of the obstacle contact's kernels."""
    mods = loaded_modules(scene="hanging", solver="explicit")
    assert "warp_cloth.collision.self_collision" in mods
    assert not {m for m in mods if m.startswith("warp_cloth.collision.analytic")
                or m.startswith("warp_cloth.collision.mesh_contact")}


@pytest.mark.parametrize("kw,present,absent", [
    (dict(scene="flag", self_collision=False), {"warp_cloth.forces.wind"},
     {"warp_cloth.forces.bending"}),
    (dict(scene="hanging", bending="dihedral", bend_stiffness=1e-4, self_collision=False),
     {"warp_cloth.forces.bending"}, {"warp_cloth.forces.wind", "warp_cloth.solvers.linear"}),
    (dict(scene="hanging", solver="implicit", self_collision=False),
     {"warp_cloth.solvers.implicit", "warp_cloth.solvers.linear"},
     {"warp_cloth.forces.wind", "warp_cloth.forces.bending", "warp_cloth.solvers.explicit"}),
])
def test_optional_parts_compile_only_when_used(kw, present, absent):
    mods = loaded_modules(**kw)
    assert present <= mods
    assert not (absent & mods)
