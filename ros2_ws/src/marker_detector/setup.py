from setuptools import find_packages, setup

package_name = 'marker_detector'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='body-schema maintainers',
    maintainer_email='maintainers@body-schema.invalid',
    description='ArUco hand-pose detector node',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'detector_node = marker_detector.detector_node:main',
        ],
    },
)
