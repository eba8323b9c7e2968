"""`pip install .` (not editable) ships the zoos (issue 37's bar): the package installed into
a fresh directory loads the shipped hopper zoo from another working directory."""

import os
import pathlib
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_installed_copy_loads_the_shipped_zoo(tmp_path):
    target, elsewhere, src = tmp_path / "site", tmp_path / "elsewhere", tmp_path / "src"
    elsewhere.mkdir()
    # A copy of the sources, so that the build leaves nothing in the working tree.
    shutil.copytree(ROOT / "rl2s_jax", src / "rl2s_jax",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for f in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / f, src / f)
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps",
                        "-q", "--target", str(target), str(src)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    code = ("import rl2s_jax.zoo.zoo as z; zoo = z.load_zoo('hopper'); "
            "print(z.__file__); print(zoo.size, len(zoo.test_ids))")
    env = {**os.environ, "PYTHONPATH": str(target)}
    r = subprocess.run([sys.executable, "-c", code], cwd=elsewhere, env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    module_file, sizes = r.stdout.split()[0], r.stdout.split()[1:]
    assert module_file.startswith(str(target)), module_file   # the installed copy, not the tree
    assert int(sizes[0]) > 0 and int(sizes[1]) > 0
