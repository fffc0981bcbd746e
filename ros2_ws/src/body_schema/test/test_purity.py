"""body_schema is pure Python: importing every module must not pull in rclpy."""
import pkgutil
import subprocess
import sys

import body_schema


def test_no_rclpy_import():
    mods = [m.name for m in pkgutil.iter_modules(body_schema.__path__, 'body_schema.')]
    code = ('import importlib, sys\n'
            f'for m in {mods!r}: importlib.import_module(m)\n'
            "print('rclpy' in sys.modules)")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == 'False'
    assert 'body_schema.ekf' in mods and 'body_schema.acquisition' in mods
