"""``recover``: rewrite a bag cut short by a crash into a complete MCAP file (like ``mcap recover``).

A recorder killed with SIGKILL (or a power loss) leaves a file without its summary, indexes and
footer, and maybe a torn last chunk: this project's tools read it (``calibration_interfaces.mcap_reader``)
but rosbags, mcap's default reader and ``ros2 bag`` refuse it or see no message. ``recover`` copies
every complete record (schemas, channels with their QoS, messages, the ``recording`` metadata) into
a new file that has all of them, and says what was lost.

Usage::

    recover IN.mcap [-o OUT.mcap] [--force] [--compression zstd|lz4|none]
    ros2 run calibration_bringup recover IN.mcap          # with a ROS 2 install
    python -m calibration_bringup.recover IN.mcap

Default output: ``IN.recovered.mcap`` beside the input. Exit status 0 when written, 1 when the
input cannot be read or the output exists (without ``--force``).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from calibration_interfaces import mcap_reader

__all__ = ['default_output', 'main']


def default_output(src: Path) -> Path:
    """``DIR/NAME.recovered.mcap`` for ``DIR/NAME.mcap``."""
    return src.with_name(f'{src.stem}.recovered.mcap')


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``recover``; returns the exit status."""
    ap = argparse.ArgumentParser(prog='recover', description=__doc__.split('\n\n')[0])
    ap.add_argument('bag', type=Path, help='the MCAP file to recover')
    ap.add_argument('-o', '--output', type=Path, help='the complete file to write (default: BAG.recovered.mcap)')
    ap.add_argument('--force', action='store_true', help='overwrite the output if it exists')
    ap.add_argument('--compression', default='zstd', choices=list(mcap_reader.COMPRESSIONS))
    args = ap.parse_args(argv)
    out = args.output or default_output(args.bag)
    if out.exists() and not args.force:
        print(f'recover: {out} exists (use --force to overwrite it)', file=sys.stderr)
        return 1
    try:
        source = mcap_reader.recover(args.bag, out, compression=args.compression)
    except (FileNotFoundError, ValueError) as exc:      # BagError is a ValueError
        print(f'recover: {exc}', file=sys.stderr)
        return 1
    print(source.loss or f'{args.bag} was complete: {source.message_count} messages copied')
    print(f'wrote {out}: {source.message_count} messages on {len(source.topics)} topics, with summary and indexes')
    return 0


if __name__ == '__main__':
    sys.exit(main())
