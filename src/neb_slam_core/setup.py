# Metadata lives in setup.cfg; this file lets colcon (colcon-python-setup-py) build the package too.
from setuptools import setup

setup()
