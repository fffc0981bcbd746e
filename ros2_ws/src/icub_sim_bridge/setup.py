from glob import glob

from setuptools import find_packages, setup

package_name = 'icub_sim_bridge'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (f'share/{package_name}/config', glob('config/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='body-schema maintainers',
    maintainer_email='maintainers@body-schema.invalid',
    description='PyBullet iCub right-arm simulation bridged to ROS 2',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'sim_node = icub_sim_bridge.sim_node:main',
            'sim_visibility = icub_sim_bridge.visibility:main',
        ],
    },
)
