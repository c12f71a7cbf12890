"""The science core and the message conversion import and run without rclpy, and the
core imports nothing of the package outside itself."""

import subprocess
import sys
from pathlib import Path

import neurncd_ros

PKG = Path(neurncd_ros.__file__).parent

BLOCK_RCLPY = r"""
import importlib, pkgutil, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('rclpy', 'rosidl_runtime_py', 'sensor_msgs', 'std_msgs',
                                  'geometry_msgs', 'std_srvs'):
            raise ImportError('blocked for this test: ' + name)
sys.meta_path.insert(0, Block())
import neurncd_ros.core as core, neurncd_ros.core.msgconv
mods = [m.name for m in pkgutil.walk_packages(core.__path__, 'neurncd_ros.core.')]
for m in mods:
    importlib.import_module(m)
outside = sorted(k for k in sys.modules if k.startswith('neurncd_ros.')
                 and not k.startswith(('neurncd_ros.core', 'neurncd_ros.config')))
assert not outside, 'the core imports outside itself: ' + ', '.join(outside)
from neurncd_ros import config
config.default()
assert not any(k.split('.')[0] == 'rclpy' for k in sys.modules)
print(len(mods))
"""


def test_core_imports_without_rclpy():
    r = subprocess.run([sys.executable, "-c", BLOCK_RCLPY], capture_output=True, text=True,
                       timeout=300, cwd=PKG.parent)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.strip()) >= 15, "fewer core modules than expected were imported"
