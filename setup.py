"""beo_ros: Bayesian Eigenobjects for ROS 2 (ament_python package)."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'beo_ros'


def model_files():
    """(install dir, [files]) pairs for every shipped model directory models/<name>/, nested
    directories included: models/<name>/<sub>/f installs to share/beo_ros/models/<name>/<sub>/f.

    Hidden files and directories are skipped (as glob('*') does); every models/<name>/ gets
    an entry, even when empty, so its share directory exists.
    """
    out = []
    for top in sorted(glob('models/*/')):
        for d, dirs, names in os.walk(top, followlinks=True):
            dirs[:] = sorted(n for n in dirs if not n.startswith('.'))
            files = sorted(os.path.join(d, n) for n in names
                           if not n.startswith('.') and os.path.isfile(os.path.join(d, n)))
            if files or d == top:
                out.append((os.path.join('share', package_name, os.path.normpath(d)), files))
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
            'beo-bag-recover = beo_ros.ros.bag:recover_main',
        ],
    },
)
