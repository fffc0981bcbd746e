from glob import glob

from setuptools import find_packages, setup

package_name = 'calibration_viz'

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
    description='Live 3D view of a calibration in the browser',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'viz_node = calibration_viz.viz_node:main',
            'bag_view = calibration_viz.bag_view:main',
        ],
    },
)
