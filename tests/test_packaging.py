"""Packaging: optional extras fail with the command that installs them, the core imports
without them, and a non-editable install finds its shipped models from any directory."""
from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from diffgns._extras import MissingExtraError, require
from diffgns.models import shipped_models

#: import names that come only with an extra (not scipy and sympy: jax needs scipy, and jax-md
#: imports sympy through e3nn-jax, so both are always installed with the core)
EXTRA_MODULES = ("skfem", "triangle", "pyoperon", "taichi", "torch", "torch_geometric")


@pytest.mark.parametrize("module, extra", [("skfem", "cfd"), ("triangle", "cfd"),
                                           ("pyoperon.sklearn", "symbolic"),
                                           ("torch", "bench")])
def test_missing_extra_names_the_pip_command(monkeypatch, module, extra):
    monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setitem(sys.modules, module.split(".")[0], None)  # as if not installed
    with pytest.raises(ImportError, match=rf"pip install diffgns\[{extra}\]") as info:
        require(module, extra)
    assert isinstance(info.value, MissingExtraError)


def test_require_returns_the_installed_module():
    assert require("numpy", "cfd") is sys.modules["numpy"]
    with pytest.raises(ValueError, match="unknown extra 'cdf'"):
        require("numpy", "cdf")


def test_error_inside_an_installed_module_is_not_blamed_on_the_extra(monkeypatch):
    """A dependency of the extra's module missing is a broken install, not a missing extra."""
    monkeypatch.setitem(sys.modules, "_diffgns_absent_dependency", None)
    with pytest.raises(ModuleNotFoundError) as info:
        require("_diffgns_absent_dependency", "cfd")  # the module itself: the extra's message
    assert isinstance(info.value, MissingExtraError)

    class Finder:  # a module "skfem_like" whose own import needs a missing one
        @staticmethod
        def find_spec(name, path=None, target=None):
            if name != "skfem_like":
                return None
            return importlib.util.spec_from_loader(name, Loader())

    class Loader:
        def create_module(self, spec):
            return None

        def exec_module(self, module):
            import _diffgns_absent_dependency  # noqa: F401

    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    with pytest.raises(ModuleNotFoundError) as info:
        require("skfem_like", "cfd")
    assert not isinstance(info.value, MissingExtraError)


@pytest.mark.parametrize("module, blocked, extra", [
    ("diffgns.mesh.geometry", "triangle", "cfd"),
    ("diffgns.mesh.fem", "skfem", "cfd"),
    ("diffgns.interpret.symbolic", "sympy", "symbolic"),
    ("diffgns.interpret.units", "sympy", "symbolic"),
])
def test_modules_needing_an_extra_say_which(monkeypatch, module, blocked, extra):
    monkeypatch.setitem(sys.modules, blocked, None)
    for name in [m for m in sys.modules if m.startswith(("diffgns.mesh", "diffgns.interpret"))]:
        monkeypatch.delitem(sys.modules, name)  # re-import from scratch; restored afterwards
    with pytest.raises(MissingExtraError, match=rf"pip install diffgns\[{extra}\]"):
        importlib.import_module(module)


_WALK = """
import importlib, json, pkgutil, sys
class NotInstalled:  # behaves as if the extras' packages were absent
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, NotInstalled())
import diffgns
from diffgns._extras import MissingExtraError
out = {{}}
for m in pkgutil.walk_packages(diffgns.__path__, "diffgns."):
    try:
        importlib.import_module(m.name)
        out[m.name] = "ok"
    except MissingExtraError as e:
        out[m.name] = "extra: " + str(e)
    except Exception as e:
        out[m.name] = "error: " + type(e).__name__ + ": " + str(e)
print(json.dumps(out))
"""


def test_core_imports_without_any_extra():
    """With every extra's modules blocked, each diffgns module imports, or (only under
    diffgns.mesh and diffgns.interpret) fails with the extra's message -- never a bare
    ModuleNotFoundError. The MPM, GNS, hybrid, inverse, scene, io and cli packages import."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    res = subprocess.run([sys.executable, "-c", _WALK.format(blocked=EXTRA_MODULES)],
                         capture_output=True, text=True, env=env, timeout=300, check=True)
    status = json.loads(res.stdout.strip().splitlines()[-1])
    core = [m for m in status if not m.startswith(("diffgns.mesh.", "diffgns.interpret."))]
    for pkg in ("mpm", "graph", "hybrid", "inverse", "scene", "io", "cli"):
        assert any(m.startswith(f"diffgns.{pkg}") for m in core), pkg
    assert {m: s for m, s in status.items() if m in core and s != "ok"} == {}
    errors = {m: s for m, s in status.items() if s.startswith("error")}
    assert errors == {}
    needing = {m for m, s in status.items() if s.startswith("extra")}
    assert {"diffgns.mesh.geometry", "diffgns.mesh.fem", "diffgns.mesh.cfd"} <= needing
    assert "diffgns.mesh.meshnet" not in needing  # the MeshGraphNet model itself is core JAX


_INSTALLED = """
import json, sys
import diffgns
from diffgns.graph.train_loop import load_model
from diffgns.interpret import message_net
from diffgns.mesh.train import load_model as load_mesh_model
from diffgns.models import model_path, models_root, shipped_models
gns, params, info = load_model(model_path("gns_columns"))
load_mesh_model(model_path("meshnet_cylinder/model"))
message_net.load(model_path("message_net_spring_l1/model"))
print(json.dumps(dict(package=diffgns.__file__, root=str(models_root()),
                      models=shipped_models(), radius=gns.config.radius,
                      factor=info["factor"],
                      logs=sorted(p.name for p in models_root().rglob("*.csv")))))
"""


def test_non_editable_install_loads_shipped_models_from_any_directory(tmp_path):
    """``pip install .`` (a wheel, not editable) finds its shipped models from a working
    directory outside the source tree: the models are package data found through
    importlib.resources. Built from a copy of the sources, so the tree is left clean."""
    repo = Path(__file__).resolve().parents[1]
    copy = tmp_path / "source"
    copy.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(repo / name, copy / name)
    shutil.copytree(repo / "src", copy / "src",
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w",
                    str(tmp_path / "dist"), str(copy)], check=True, timeout=300)
    (wheel,) = (tmp_path / "dist").glob("diffgns-*.whl")
    site = tmp_path / "site"
    subprocess.run([*pip, "install", "--no-deps", "--no-compile", "--target", str(site),
                    str(wheel)], check=True, timeout=300)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "JAX_PLATFORMS": "cpu"}
    res = subprocess.run([sys.executable, "-c", _INSTALLED], cwd=elsewhere, env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert Path(out["package"]).is_relative_to(site)  # the wheel, not the source tree
    assert Path(out["root"]).is_relative_to(site)
    assert out["models"] == shipped_models() and len(out["models"]) >= 10
    assert out["radius"] > 0 and out["factor"] == 4
    assert out["logs"] == []  # training logs stay in the source tree
