import pathlib
import sys
import types

ROOT = pathlib.Path(__file__).resolve().parents[2]
mod = types.ModuleType("tests_paths")
mod.INSTALL = ROOT / "ros_ws" / "install"
sys.modules["tests_paths"] = mod
