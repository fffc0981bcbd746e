"""Symlink each package's setup.py ``data_files`` into a prefix, as ``colcon build --symlink-install``.

Editable pip installs do not install ``data_files`` (ament index markers, package.xml, config), so
after ``pip install -e`` this puts them where ament_index_python looks: ``<prefix>/share/...``.
Usage: python install_data_files.py PREFIX PKG_DIR...
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import setuptools  # noqa: F401  (provides distutils on Python >= 3.12 and patches it here)
from distutils.core import run_setup


def data_files_of(pkg_dir: Path) -> list[tuple[str, list[str]]]:
    """Return the ``data_files`` declared by ``pkg_dir/setup.py`` without building anything."""
    cwd = os.getcwd()
    os.chdir(pkg_dir)
    try:
        dist = run_setup('setup.py', stop_after='init')
    finally:
        os.chdir(cwd)
    return list(dist.data_files or [])


def main(argv: list[str]) -> int:
    prefix = Path(argv[1]).resolve()
    for pkg in argv[2:]:
        pkg_dir = Path(pkg).resolve()
        for dest, files in data_files_of(pkg_dir):
            target_dir = prefix / dest
            target_dir.mkdir(parents=True, exist_ok=True)
            for f in files:
                src = pkg_dir / f
                link = target_dir / src.name
                if link.is_symlink() or link.exists():
                    if link.is_symlink() and link.resolve() == src:
                        continue
                    link.unlink()
                link.symlink_to(src)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
