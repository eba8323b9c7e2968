"""Quiet start: MJX's lines about its absent optional Warp backend are dropped, nothing else."""
import sys

from rl2s_jax._quiet import import_quietly


def test_import_quietly_drops_only_the_absent_warp_lines(tmp_path, monkeypatch, capsys):
    (tmp_path / "probe_like_mjx.py").write_text(
        "print(\"Failed to import warp: No module named 'warp'\")\n"
        "print(\"Failed to import mujoco_warp: No module named 'warp'\")\n"
        "print('Failed to import warp: libcuda.so.1: cannot open shared object file')\n"
        "print('something else the module says')\n"
        "LOADED = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "probe_like_mjx", raising=False)
    import_quietly("probe_like_mjx")
    out = capsys.readouterr().out.splitlines()
    assert out == ["Failed to import warp: libcuda.so.1: cannot open shared object file",
                   "something else the module says"]
    assert sys.modules["probe_like_mjx"].LOADED
    import_quietly("probe_like_mjx")  # imported once only
    assert capsys.readouterr().out == ""


def test_import_quietly_leaves_a_missing_module_to_the_real_import(capsys):
    import_quietly("no_such_module_rl2s")
    assert capsys.readouterr().out == ""
    assert "no_such_module_rl2s" not in sys.modules

