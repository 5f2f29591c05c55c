"""The ``robot_mesh: lowpoly | stock`` switch: a Panda whose visual meshes are its collision meshes.

The stock Panda's 135k-triangle visual meshes dominate software rendering (SIM.md: ~41 ms per
64x64 frame vs ~2 ms). The low-poly copy rewrites ``panda_v2.urdf`` so each ``visual/*.glb`` mesh
points at the ``collision/*.stl`` mesh shipped in the same wheel; kinematics and collisions are
unchanged. mplib reads ``<urdf>.replace('.urdf', '.srdf')``, so the .srdf is copied beside it.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from stages.common.vulkan import REPO_ROOT

ROBOT_MESHES = ("lowpoly", "stock")
_CACHE_DIR = REPO_ROOT / ".deps" / "panda_lowpoly"


def _stock_urdf() -> Path:
    from mani_skill import PACKAGE_ASSET_DIR

    return Path(PACKAGE_ASSET_DIR) / "robots" / "panda" / "panda_v2.urdf"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def lowpoly_urdf() -> Path:
    """Path of the low-poly Panda URDF (written once into ``.deps/panda_lowpoly``), with its .srdf."""
    stock = _stock_urdf()
    # relative, because mplib joins every mesh path (even an absolute one) onto the URDF's folder
    mesh_root = os.path.relpath(stock.parent, _CACHE_DIR)
    text = stock.read_text()

    def to_collision(m: re.Match) -> str:
        return f'filename="{mesh_root}/franka_description/meshes/collision/{m.group(1)}.stl"'

    text, n = re.subn(r'filename="franka_description/meshes/visual/(\w+)\.glb"', to_collision, text)
    if n == 0:
        raise RuntimeError(f"no visual meshes found to replace in {stock}; has mani-skill changed its Panda URDF?")
    # remaining relative mesh paths (collision meshes) must resolve from the new location too
    text = text.replace('filename="franka_description/', f'filename="{mesh_root}/franka_description/')
    _CACHE_DIR.mkdir(parents=True, exist_ok=True)
    urdf = _CACHE_DIR / "panda_v2_lowpoly.urdf"
    srdf = urdf.with_suffix(".srdf")
    if not urdf.is_file() or urdf.read_text() != text:
        _atomic_write(urdf, text)
    srdf_text = stock.with_suffix(".srdf").read_text()
    if not srdf.is_file() or srdf.read_text() != srdf_text:
        _atomic_write(srdf, srdf_text)
    return urdf


def use_robot_mesh(robot_mesh: str) -> None:
    """Point ManiSkill's Panda at the low-poly or the stock URDF (before the env is made)."""
    if robot_mesh not in ROBOT_MESHES:
        raise ValueError(f"robot_mesh={robot_mesh!r}; expected one of {ROBOT_MESHES}")
    from mani_skill.agents.robots import Panda

    Panda.urdf_path = str(lowpoly_urdf() if robot_mesh == "lowpoly" else _stock_urdf())
