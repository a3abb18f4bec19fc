import importlib.util
import os
import shutil
import sys
from glob import glob

from setuptools import Extension, find_packages, setup
from setuptools.command.build_ext import build_ext

package_name = 'starleth_sim'
HERE = os.path.dirname(os.path.abspath(__file__))
# starleth_interface.c_extension (standard library only: the build recipe of every C
# extension) imported from this source tree, which nothing has installed yet
sys.path.insert(0, HERE)
from starleth_interface import c_extension  # noqa: E402


def _kernel_build():
    """starleth_sim/physics/kernels/build.py, loaded by path (importing it as a module would
    import starleth_sim, whose requirements are not installed yet)."""
    path = os.path.join(HERE, package_name, 'physics', 'kernels', 'build.py')
    spec = importlib.util.spec_from_file_location('_starleth_kernel_build', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildKernels(build_ext):
    """Builds the C extensions: the physics kernels with starleth_sim/physics/kernels/build.py,
    the controller's kernels and sim_node's command parsers with
    starleth_interface/c_extension.py (the recipe of both: the flags that keep the results
    bit for bit); the same builds as a source checkout's."""

    def build_extension(self, ext):
        out = self.get_ext_fullpath(ext.name)
        if ext.name == KERNELS.name:
            kb = _kernel_build()
            seconds, inplace = kb.build(out), kb.inplace_path()
        else:
            csrc = os.path.join(HERE, os.path.dirname(ext.sources[0]))
            seconds = c_extension.build(csrc, out)
            inplace = os.path.join(os.path.dirname(csrc), os.path.basename(out))
        print(f'built {ext.name} ({out}) in {seconds:.1f} s')
        if getattr(self, 'editable_mode', False) and not self.inplace:
            # an editable install copies the module into the source tree: its digest too,
            # which tells the loader (c_extension.ensure_built) that the module is current
            shutil.copyfile(out + c_extension.DIGEST_SUFFIX, inplace + c_extension.DIGEST_SUFFIX)


KERNELS = Extension('starleth_sim.physics.kernels._kernels',
                    sources=sorted(glob('starleth_sim/physics/csrc/*.c')),
                    depends=sorted(glob('starleth_sim/physics/csrc/*.h')
                                   + glob('starleth_interface/csrc/*.h')))
#: the controller's kernels and sim_node's command parsers (starleth_interface.c_extension:
#: the sources in csrc/ of the module's package)
SMALL_EXTENSIONS = [
    Extension(module, sources=sorted(glob(f'{csrc}/*.c')),
              depends=sorted(glob(f'{csrc}/*.h') + glob('starleth_interface/csrc/*.h')))
    for module in c_extension.EXTENSIONS
    for csrc in [module.rpartition('.')[0].replace('.', '/') + '/csrc']]

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    ext_modules=[KERNELS, *SMALL_EXTENSIONS],
    cmdclass={'build_ext': BuildKernels},
    package_data={package_name: ['tools/view/page.html']},   # starleth-view's page template
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/urdf', glob('urdf/*.urdf') + glob('urdf/*.xml')),
        ('share/' + package_name + '/robots', glob('robots/*.yaml')),   # the robot library
        ('share/' + package_name + '/config', glob('config/*.yaml')),   # ros2_control
        ('share/' + package_name + '/msg_configs', glob('msg_configs/*.yaml')),
        ('share/' + package_name + '/msg_configs/terrain', glob('msg_configs/terrain/*.yaml')),
        ('share/' + package_name + '/msg_configs/actuators',
         glob('msg_configs/actuators/*.yaml')),     # the drive models' actuator: overlays
        ('share/' + package_name + '/launch', glob('launch/*.launch.xml')),
        ('share/' + package_name + '/foxglove', glob('foxglove/*.json')),
        ('share/' + package_name + '/sweeps', glob('sweeps/*.yaml')),   # starleth-sweep specs
        # the sensor models' sensors: overlays
        ('share/' + package_name + '/msg_configs/sensors', glob('msg_configs/sensors/*.yaml')),
    ],
    install_requires=[
        'setuptools',
        'numpy',
        'pyyaml',
        'pin',
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
                    'parquet': ['pyarrow'],    # starleth-sweep's results.parquet
                    'live': ['foxglove-sdk>=0.30', 'websockets']},   # sim_node live_view
    entry_points={
        'console_scripts': [
            'sim_node = starleth_sim.ros.sim_node:main',
            'controller_node = starleth_controller.controller_node:main',
            'sim_node_composed = starleth_sim.ros.sim_node:main_composed',
            'starleth-bench = starleth_sim.tools.bench.bench:main',
            'starleth-bench-ros = starleth_sim.tools.bench.ros:main',
            'starleth-bench-floor = starleth_sim.tools.bench.floor:main',
            'starleth-demo = starleth_sim.tools.demo.demo:main',
            'starleth-eval = starleth_sim.tools.evaluation.evaluation:main',
            'starleth-analyze = starleth_sim.tools.analysis.analysis:main',
            'starleth-view = starleth_sim.tools.view.view:main',
            'starleth-layout = starleth_sim.tools.view.foxglove_layout:main',
            'starleth-replay = starleth_sim.tools.replay.replay:main',
            'starleth-sweep = starleth_sim.tools.sweep.sweep:main',
            'starleth-precompile = starleth_sim.tools.precompile:main',
            'starleth-ros2-controllers = starleth_sim.ros.ros2_control_controllers:main',
        ],
    },
)
