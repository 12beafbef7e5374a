"""beo_ros: Bayesian Eigenobjects for ROS 2 (ament_python package)."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'beo_ros'


def model_files():
    """(install dir, [files]) pairs for every shipped model directory."""
    out = []
    for d in sorted(glob('models/*/')):
        files = [f for f in glob(os.path.join(d, '*')) if os.path.isfile(f)]
        out.append((os.path.join('share', package_name, d.rstrip('/')), files))
    return out


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ] + model_files(),
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='beo_ros developers',
    maintainer_email='beo-ros@example.org',
    description='Bayesian Eigenobjects: classify, orient and complete objects from one partial view',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'beo_node = beo_ros.ros.node:main',
            'beo-node = beo_ros.ros.node:main',
            'beo-train = beo_ros.train:main',
            'beo-eval = beo_ros.evaluate:main',
            'beo-bench = beo_ros.bench:main',
            'beo-demo = beo_ros.ros.demo:main',
            'beo-replay = beo_ros.ros.bag:replay_main',
            'beo-record = beo_ros.ros.bag:record_main',
            'beo-pcd2bag = beo_ros.ros.bag:pcd2bag_main',
        ],
    },
)
