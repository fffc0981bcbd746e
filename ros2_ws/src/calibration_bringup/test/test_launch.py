"""launch/calibration.launch.py: there is no ``launch`` package here, so the file is compiled and
its node table checked against what exists: installed executables, parameter files, declared
parameters, and the same nodes as scripts/run_calibration.sh."""
from __future__ import annotations

import importlib
import importlib.metadata as md
import importlib.util
import inspect
import re
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_share_directory
from rclpy.node import Node
from rclpy.parameter import Parameter

PKG = Path(__file__).resolve().parents[1]
LAUNCH = PKG / 'launch' / 'calibration.launch.py'
SCRIPT = PKG.parents[2] / 'scripts' / 'run_calibration.sh'


def _launch_module():
    spec = importlib.util.spec_from_file_location('calibration_launch', LAUNCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _specs(tmp_path: Path, **overrides: str) -> list[dict]:
    mod = _launch_module()
    args = {k: d for k, (d, _) in mod.ARGUMENTS.items()}
    return mod.node_specs({**args, 'output': str(tmp_path), **overrides})


def _node_class(package: str, executable: str) -> type:
    (ep,) = [e for e in md.distribution(package).entry_points
             if e.group == 'console_scripts' and e.name == executable]
    module = importlib.import_module(ep.module)
    (cls,) = [c for c in vars(module).values()
              if inspect.isclass(c) and issubclass(c, Node) and c is not Node and c.__module__ == module.__name__]
    return cls


def test_the_launch_file_compiles_and_is_installed() -> None:
    compile(LAUNCH.read_text(), str(LAUNCH), 'exec')
    assert callable(_launch_module().generate_launch_description)
    installed = Path(get_package_share_directory('calibration_bringup')) / 'launch' / LAUNCH.name
    assert installed.is_file() and installed.read_bytes() == LAUNCH.read_bytes()


def test_it_starts_the_nodes_run_calibration_starts_with_existing_parameter_files(tmp_path: Path) -> None:
    specs = _specs(tmp_path)
    started = {(s['package'], s['executable']) for s in specs}
    in_script = set(re.findall(r'^start \w+ (\w+) (\w+) ', SCRIPT.read_text(), re.M))
    assert started == in_script and len(started) == 5
    config = Path(get_package_share_directory('calibration_bringup')) / 'config'
    for s in specs:
        assert (config / s['params_file']).is_file(), s
        _node_class(s['package'], s['executable'])          # the executable exists and has a node
    assert specs[0]['executable'] == 'recorder_node', 'the recorder starts first'


def test_viz_adds_the_live_view_with_its_own_parameter_file(tmp_path: Path) -> None:
    (viz,) = [s for s in _specs(tmp_path, viz='true') if s not in _specs(tmp_path)]
    assert (viz['package'], viz['executable']) == ('calibration_viz', 'viz_node')
    assert (Path(get_package_share_directory(viz['config_package'])) / 'config' / viz['params_file']).is_file()
    _node_class(viz['package'], viz['executable'])
    with pytest.raises(ValueError, match='yes'):
        _specs(tmp_path, viz='yes')


def test_every_override_is_declared_by_its_node(ros, tmp_path: Path) -> None:
    """A misspelt parameter would be silently ignored by a launched node."""
    for s in _specs(tmp_path, noise='constant', robot='ur5e', viz='true'):
        cls = _node_class(s['package'], s['executable'])
        overrides = [Parameter(k, value=v) for k, v in s['parameters'].items()]
        node = ros.add(cls(context=ros.context, parameter_overrides=overrides))
        for name, value in s['parameters'].items():
            assert node.has_parameter(name), f"{s['executable']} does not declare {name!r}"
            assert node.get_parameter(name).value == value
        if hasattr(node, 'close'):
            node.close()


def test_bad_noise_model_is_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match='pdn'):
        _specs(tmp_path, noise='pdn')


def test_transport_encoding_and_calibration_file_reach_their_nodes(tmp_path: Path) -> None:
    def by_name(**args: str) -> dict[str, dict]:
        return {s['name']: s['parameters'] for s in _specs(tmp_path, **args)}

    raw = by_name()
    assert raw['sim']['compressed_format'] == 'none' and raw['sim']['image_encoding'] == 'rgb8'
    assert raw['detector'] == {'robot': 'icub_right_arm', 'transport': 'raw'}
    assert raw['recorder']['exclude'] == ['/camera/left/image_raw/compressed', '/camera/right/image_raw/compressed']
    url = f'file://{tmp_path}/ost.yaml'
    packed = by_name(transport='compressed', image_encoding='bayer_rggb8', camera_info_url=url, viz='true')
    assert packed['sim']['compressed_format'] == 'jpeg' and packed['sim']['image_encoding'] == 'bayer_rggb8'
    assert packed['detector'] == {'robot': 'icub_right_arm', 'transport': 'compressed', 'camera_info_url': url}
    assert packed['recorder']['exclude'] == ['/camera/left/image_raw', '/camera/right/image_raw']
    assert packed['viz']['transport'] == 'compressed'
    with pytest.raises(ValueError, match='theora'):
        _specs(tmp_path, transport='theora')
    with pytest.raises(ValueError, match='nv24'):
        _specs(tmp_path, image_encoding='nv24')
