from glob import glob

from setuptools import find_packages, setup

package_name = 'starleth_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={package_name: ['tools/view_page.html']},   # starleth-view's page template
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/urdf', glob('urdf/*.urdf')),
        ('share/' + package_name + '/msg_configs', glob('msg_configs/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.xml')),
        ('share/' + package_name + '/foxglove', glob('foxglove/*.json')),
        ('share/' + package_name + '/sweeps', glob('sweeps/*.yaml')),   # starleth-sweep specs
    ],
    install_requires=[
        'setuptools',
        'numpy',
        'pyyaml',
        'pin',
        'numba',
        'mcap',
        'mcap-ros2-support',
        'matplotlib',
        'proxsuite',
        'meshcat',
    ],
    zip_safe=False,
    maintainer='StarlETH sim developers',
    maintainer_email='dev@example.com',
    description='Python simulator of the StarlETH quadruped with a ROS 2 interface.',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest'],
                    'ray': ['ray>=2.9'],       # starleth-sweep / starleth-eval --ray
                    'parquet': ['pyarrow']},   # starleth-sweep's results.parquet
    entry_points={
        'console_scripts': [
            'sim_node = starleth_sim.ros.sim_node:main',
            'controller_node = starleth_controller.controller_node:main',
            'sim_node_composed = starleth_sim.ros.sim_node:main_composed',
            'starleth-bench = starleth_sim.tools.bench:main',
            'starleth-bench-ros = starleth_sim.tools.bench_ros:main',
            'starleth-bench-floor = starleth_sim.tools.bench_floor:main',
            'starleth-demo = starleth_sim.tools.demo:main',
            'starleth-eval = starleth_sim.tools.evaluation:main',
            'starleth-analyze = starleth_sim.tools.analysis:main',
            'starleth-view = starleth_sim.tools.view:main',
            'starleth-replay = starleth_sim.tools.replay:main',
            'starleth-sweep = starleth_sim.tools.sweep:main',
            'starleth-precompile = starleth_sim.tools.precompile:main',
        ],
    },
)
