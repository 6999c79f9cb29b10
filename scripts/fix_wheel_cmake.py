#!/usr/bin/env python3
"""Rewrite the wheel build machine's include folders in the ROS wheels' CMake exports.

The ros-jazzy-* wheels export ``*__rosidl_generator_py`` targets whose
INTERFACE_INCLUDE_DIRECTORIES name /opt/python/cp311-cp311/include/python3.11
and that machine's numpy include folder. CMake then refuses to configure any
package that generates Python interfaces ("Imported target ... includes
non-existent path"). This script replaces those two paths by the local Python
and numpy include folders. It is idempotent: a second run changes nothing.
"""
import glob
import os
import re
import sys
import sysconfig

import numpy

prefix = sys.argv[1] if len(sys.argv) > 1 else sys.prefix
py_inc = sysconfig.get_paths()["include"]
np_inc = numpy.get_include()
pattern = re.compile(r"/opt/python/cp3\d+-cp3\d+/(?:include/python3\.\d+|lib/python3\.\d+/site-packages/numpy/(?:_core|core)/include)")

changed = 0
for path in glob.glob(os.path.join(prefix, "share", "*", "cmake", "*.cmake")):
    with open(path, encoding="utf-8") as f:
        text = f.read()
    if "/opt/python/" not in text:
        continue
    new = pattern.sub(lambda m: np_inc if "numpy" in m.group(0) else py_inc, text)
    if new != text:
        with open(path, "w", encoding="utf-8") as f:
            f.write(new)
        changed += 1
print(f"fix_wheel_cmake: rewrote {changed} file(s) (python include {py_inc}, numpy include {np_inc})")
