"""neuralrt: neural ray intersection (NIF, N-BVH, LSNIF) beside exact Embree ray tracing."""

from .accel.blas import BLAS, MemoryReport
from .accel.mesh_blas import MeshBLAS
from .errors import NeuralRTError
from .geometry.mesh import Mesh, load_mesh
from .rays import AABB, Hits, Rays, Transform

__version__ = "0.1.0"

__all__ = ["AABB", "BLAS", "Hits", "Mesh", "MeshBLAS", "MemoryReport", "NeuralRTError", "Rays", "Transform", "load_mesh"]
