from glob import glob

from setuptools import find_packages, setup

package_name = 'dh_estimator'

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
    description='Online EKF estimation of DH parameters',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'estimator_node = dh_estimator.estimator_node:main',
            'evaluate = dh_estimator.evaluate:main',
        ],
    },
)
