"""Metadata lives in setup.cfg; this file builds the map's C++ kernels (``neb_slam_core.scene._map_kernels``,
from ``scene/csrc/map_kernels.cpp``) as a torch extension, and lets colcon (colcon-python-setup-py) build the
package too.

The build needs torch importable while installing: ``pip install --no-build-isolation`` (as the Makefile
does) or colcon from the venv. Without torch, or when the compile fails, the package installs without the
module, and ``scene/_ext.py`` compiles the same source on first use instead.
"""

import importlib.util
import sys
from pathlib import Path

from setuptools import setup

HERE = Path(__file__).resolve().parent
EXT_PY = HERE / "neb_slam_core" / "scene" / "_ext.py"


def _ext_helpers():
    """``scene/_ext.py`` loaded on its own (not the package): the flags, build key and names it uses."""
    spec = importlib.util.spec_from_file_location("_neb_slam_ext_for_setup", EXT_PY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def kernel_build() -> dict:
    """``setup()`` arguments that build the kernels' module; none when torch is not importable."""
    try:
        from torch.utils.cpp_extension import BuildExtension, CppExtension
    except ImportError as exc:
        print(
            f"neb_slam_core: torch is not importable here ({exc}): the C++ kernels are not built now; "
            "they compile on first use instead",
            file=sys.stderr,
        )
        return {}

    class OptionalBuildExtension(BuildExtension):
        """A failed build (no compiler, a compile error) leaves the package without the module: the install
        goes on, and the first-use build tries again (and reports why it fails, if it does)."""

        def run(self):
            try:
                super().run()
            except Exception as exc:
                print(
                    f"neb_slam_core: building the C++ kernels failed ({type(exc).__name__}: {exc}); they "
                    "compile on first use instead",
                    file=sys.stderr,
                )

    ext = _ext_helpers()
    flags = ext.compile_flags()
    # -fno-wrapv -g0: undo what Python's own CFLAGS add to an extension build (-fwrapv, -g), so that this
    # build compiles like the first-use one (torch's JIT does not add them)
    extension = CppExtension(
        ext.INSTALLED,
        sources=[str(ext.SOURCE.relative_to(HERE))],
        extra_compile_args=flags + ["-fno-wrapv", "-g0", ext.key_define(ext.build_key(flags))],
        extra_link_args=["-fopenmp"],
    )
    return {"ext_modules": [extension], "cmdclass": {"build_ext": OptionalBuildExtension}}


setup(**kernel_build())
