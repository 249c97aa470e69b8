"""OpenFusion-Z: real-time open-vocabulary 3D mapping over Eclipse Zenoh.

The library lives in ``openfusion`` (source folder ``shared/openfusion``); the services in
``openfusion.services`` (source folder ``services/``). See docs/ARCHITECTURE.md.
"""

__version__ = "0.1.0"
