"""Node parameters described once, on the settings dataclasses (no rclpy).

A settings field becomes a ROS parameter when it is declared with :func:`setting`: the field's
default is the parameter's default (its Python type is the parameter's type, so write ``0.05``,
not ``0``), and the description, range and allowed values sit next to it. The node declares its
parameters from the dataclass (:func:`calibration_interfaces.node_util.declare_settings`) and the
documentation's parameter tables (README and docs pages, between ``<!-- parameters: ... -->``
markers) are checked against :func:`markdown_table`, so each parameter has one default, one
description and one range.

Examples
--------
>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Demo:
...     rate: float = setting(2.5, 'Camera rate [Hz]', (0.0, 60.0))
>>> [(s.name, s.default, s.range) for s in parameter_specs(Demo)]
[('rate', 2.5, (0.0, 60.0))]
"""
from __future__ import annotations

import dataclasses
import importlib
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ['setting', 'ParameterSpec', 'parameter_specs', 'settings_from_parameters', 'markdown_table',
           'read_params_file', 'update_tables', 'main']

_KEY = 'ros_parameter'


@dataclass(frozen=True)
class ParameterSpec:
    """One ROS parameter described by a settings field.

    Attributes
    ----------
    field : str
        The dataclass field.
    name : str
        The parameter name (the field name unless the field says otherwise).
    default : Any
        The default; tuples are declared as ROS arrays. ``()`` declares an array of
        ``array_type`` without a value (rclpy cannot type an empty list); unset reads as ``()``.
    description : str
    range : tuple of two numbers, or None
        Inclusive bounds (float or integer range, by the default's type).
    choices : tuple of str, or None
        Allowed values of a string parameter.
    """

    field: str
    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    array_type: str = 'string'

    @property
    def full_description(self) -> str:
        """The description, with the allowed values when there are any."""
        if not self.choices:
            return self.description
        return f"{self.description} ({' | '.join(self.choices)})"


def setting(default: Any, description: str, range: tuple[float, float] | None = None, *,  # noqa: A002
            choices: Sequence[str] | None = None, name: str | None = None, array_type: str = 'string') -> Any:
    """A dataclass field that is also a ROS parameter (see the module docstring).

    Parameters
    ----------
    default : bool, int, float, str or tuple
        Default value; its type is the parameter's type.
    description : str
        What it sets, with its unit in brackets.
    range : (lo, hi), optional
        Inclusive bounds of a numeric parameter.
    choices : sequence of str, optional
        Allowed values of a string parameter.
    name : str, optional
        Parameter name when it differs from the field name.
    array_type : {'string', 'double', 'integer'}
        Element type of an array parameter whose default is empty.
    """
    if isinstance(default, list):
        raise TypeError(f'setting default {default!r}: use a tuple (settings are frozen)')
    if range is not None and not isinstance(default, (int, float)):
        raise TypeError(f'setting default {default!r}: a range needs a numeric default')
    if array_type not in ('string', 'double', 'integer'):
        raise ValueError(f"array_type must be 'string', 'double' or 'integer', got {array_type!r}")
    meta = {_KEY: {'description': description, 'range': range,
                   'choices': tuple(choices) if choices is not None else None, 'name': name,
                   'array_type': array_type}}
    return dataclasses.field(default=default, metadata=meta)


def parameter_specs(settings: type | Any) -> list[ParameterSpec]:
    """The parameters a settings dataclass (class or instance) declares, in field order."""
    specs = []
    for f in dataclasses.fields(settings):
        meta = f.metadata.get(_KEY)
        if meta is None:
            continue
        specs.append(ParameterSpec(f.name, meta['name'] or f.name, f.default, meta['description'],
                                   meta['range'], meta['choices'], meta['array_type']))
    return specs


def settings_from_parameters(cls: type, values: Mapping[str, Any], **fixed: Any) -> Any:
    """Build ``cls`` from parameter values keyed by parameter name.

    Lists become tuples; values of fields without a parameter come from ``fixed`` or the
    dataclass defaults.

    Raises
    ------
    ValueError
        If a string parameter is not one of its choices; the message names the parameter,
        the value and the choices.
    """
    kwargs = dict(fixed)
    for spec in parameter_specs(cls):
        if spec.name not in values:
            continue
        value = values[spec.name]
        if isinstance(value, list):
            value = tuple(value)
        if spec.choices is not None and value not in spec.choices:
            raise ValueError(f'parameter {spec.name}: {value!r} is not one of {list(spec.choices)}')
        kwargs[spec.field] = value
    return cls(**kwargs)


def _cell(value: Any) -> str:
    if isinstance(value, str):
        return f"`'{value}'`"
    if isinstance(value, tuple):
        return '`[' + ', '.join(str(v) for v in value) + ']`'
    if isinstance(value, bool):
        return f'`{str(value).lower()}`'
    return f'`{value}`'


def markdown_table(*settings: type) -> str:
    """The parameter table of one node's settings dataclasses, as the documentation shows it.

    Columns: parameter, default, range or choices, description.
    """
    lines = ['| parameter | default | range | description |', '|---|---|---|---|']
    for cls in settings:
        for s in parameter_specs(cls):
            rng = (f'{s.range[0]} .. {s.range[1]}' if s.range is not None
                   else ' \\| '.join(s.choices) if s.choices else '')
            lines.append(f'| `{s.name}` | {_cell(s.default)} | {rng} | {s.description} |')
    return '\n'.join(lines)


def read_params_file(path: str | Path, node: str) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` in a ROS 2 parameter file (``--params-file``).

    Lets a tool without rclpy (the offline evaluation) use the settings a run used.

    Raises
    ------
    ValueError
        If the file has no ``<node>: ros__parameters:`` mapping; the message names the file.
    """
    import yaml

    doc = yaml.safe_load(Path(path).read_text()) or {}
    section = doc.get(node, doc.get(f'/{node}', {})) if isinstance(doc, dict) else {}
    values = section.get('ros__parameters') if isinstance(section, dict) else None
    if not isinstance(values, dict):
        raise ValueError(f'{path}: no "{node}: ros__parameters:" mapping')
    return values


_BLOCK = re.compile(r'(<!-- parameters: ([^>]*?) -->\n)(.*?)(<!-- /parameters -->)', re.S)


def _resolve(ref: str) -> type:
    module, _, name = ref.strip().partition(':')
    return getattr(importlib.import_module(module), name)


def update_tables(text: str) -> str:
    """``text`` with every generated parameter table rewritten from its settings classes.

    A table sits between ``<!-- parameters: pkg.module:Class, ... -->`` and
    ``<!-- /parameters -->``; :func:`markdown_table` of the listed classes replaces it. A page
    is up to date when this returns it unchanged (the test suite checks the READMEs and docs/).
    """
    def render(m: re.Match[str]) -> str:
        classes = [_resolve(r) for r in m.group(2).split(',')]
        return f'{m.group(1)}{markdown_table(*classes)}\n{m.group(4)}'

    return _BLOCK.sub(render, text)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m calibration_interfaces.parameters FILE...``: regenerate the tables in place."""
    import sys

    for path in (sys.argv[1:] if argv is None else argv):
        p = Path(path)
        text = p.read_text()
        new = update_tables(text)
        if new != text:
            p.write_text(new)
            print(f'updated {p}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
