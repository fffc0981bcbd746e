from glob import glob

from setuptools import find_packages, setup

package_name = 'calibration_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (f'share/{package_name}/config', glob('config/*')),
        (f'share/{package_name}/launch', glob('launch/*.launch.py')),
        (f'share/{package_name}/msg_definitions/tf2_msgs/msg', glob('msg_definitions/tf2_msgs/msg/*.msg')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='body-schema maintainers',
    maintainer_email='maintainers@body-schema.invalid',
    description='Launch support, MCAP recorder, replay, experiments and reports',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'calibration_report = calibration_bringup.report:main',
            'recorder_node = calibration_bringup.recorder_node:main',
            'bag_player = calibration_bringup.player_node:main',
            'experiment = calibration_bringup.experiment:main',
            'ablation = calibration_bringup.ablation:main',
            'paper_tuning = calibration_bringup.paper_tuning:main',
            'recover = calibration_bringup.recover:main',
        ],
    },
)
