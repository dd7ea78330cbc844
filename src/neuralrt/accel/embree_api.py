"""Embree 4's C API, called from numba kernels: a triangle scene built through ctypes, and the
two per-ray queries (`rtcIntersect1`, `rtcOccluded1`) as numba intrinsics.

Why not embreex's Python API: its ``run`` is a serial loop over the rays, so every parallel chunk
cost a Python thread hand-off, and the passes before and after it (validation, hit attributes) ran
as separate calls. Called from a numba kernel, one parallel region on OpenMP's threads (the ones
torch and our other kernels use, still spinning from the previous region) validates, traces and
interpolates each ray: `MeshBLAS.intersect` of 8,192 bunny rays 2.25-2.42 -> 1.34-1.57 ms right
after a parallel region (docs/lsnif.md, session 45). The library is the one embreex's wheel ships
(``embreex.libs/libembree4*``); its symbols are registered with LLVM under our own names, so a
cached kernel finds them in every process and no other Embree build in the process can be picked.
"""

from __future__ import annotations

import ctypes
import glob
import importlib.util
import os
import weakref

import numba
import numpy as np
from llvmlite import binding as llvm
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

__all__ = ["TriangleScene", "rtc_intersect1", "rtc_occluded1", "ray_record", "INVALID_ID"]

# struct RTCRayHit (Embree 4, rtcore_ray.h), as 4-byte words: RTCRay is org_x, org_y, org_z, tnear,
# dir_x, dir_y, dir_z, time, tfar, mask, id, flags (48 B); RTCHit follows: Ng_x, Ng_y, Ng_z, u, v,
# primID, geomID, instID[...]. RTCRay alone is what rtcOccluded1 takes (tfar = -inf when blocked).
ORG, TNEAR, DIR, TIME, TFAR, MASK, RAY_ID, FLAGS = 0, 3, 4, 7, 8, 9, 10, 11
HIT_U, HIT_V, PRIM_ID, GEOM_ID, INST_ID = 15, 16, 17, 18, 19
# Words per record: more than RTCRayHit's 28 (instance arrays, more instance levels in another
# build only add words after instID[0]); records are 64-byte aligned (Embree wants 16).
RECORD_WORDS = 48
INVALID_ID = np.uint32(0xFFFFFFFF)  # RTC_INVALID_GEOMETRY_ID

_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
# Watertight: rays through a shared edge or vertex find a triangle (embreex builds its scenes so).
_SCENE_FLAG_ROBUST = 1 << 2
_ERRORS = {1: "unknown error", 2: "invalid argument", 3: "invalid operation", 4: "out of memory",
           5: "unsupported CPU", 6: "cancelled", 7: "level zero error"}  # fmt: skip

_SYMBOL_PREFIX = "neuralrt_"  # LLVM names of Embree's entry points (`library` registers them)
_library: ctypes.CDLL | None = None
_device: tuple[int, int] | None = None  # (process id, RTCDevice): one device per process


def _library_path() -> str:
    """Embree 4 as embreex's wheel ships it (Linux: ``embreex.libs``, macOS: ``embreex/.dylibs``,
    Windows: next to the package)."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("Embree is missing: pip install embreex")
    package = spec.submodule_search_locations[0]
    for pattern in ("../embreex.libs/libembree4*", ".dylibs/libembree4*", "embree4*.dll", "../embreex.libs/embree4*.dll"):
        found = sorted(glob.glob(os.path.join(package, pattern)))
        if found:
            return found[0]
    raise RuntimeError(f"Embree 4's library was not found beside embreex ({package})")


def library() -> ctypes.CDLL:
    """The Embree library, its functions typed, its two queries registered for numba (once)."""
    global _library
    if _library is None:
        lib = ctypes.CDLL(_library_path())
        handle = ctypes.c_void_p
        for name, result, arguments in (
            ("rtcNewDevice", handle, [ctypes.c_char_p]),
            ("rtcGetDeviceError", ctypes.c_int, [handle]),
            ("rtcNewScene", handle, [handle]),
            ("rtcSetSceneFlags", None, [handle, ctypes.c_int]),
            ("rtcNewGeometry", handle, [handle, ctypes.c_int]),
            ("rtcSetNewGeometryBuffer", handle, [handle, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t]),
            ("rtcCommitGeometry", None, [handle]),
            ("rtcAttachGeometry", ctypes.c_uint, [handle, handle]),
            ("rtcReleaseGeometry", None, [handle]),
            ("rtcCommitScene", None, [handle]),
            ("rtcReleaseScene", None, [handle]),
        ):  # fmt: skip
            function = getattr(lib, name)
            function.restype, function.argtypes = result, arguments
        for name in ("rtcIntersect1", "rtcOccluded1"):
            llvm.add_symbol(_SYMBOL_PREFIX + name, ctypes.cast(getattr(lib, name), ctypes.c_void_p).value)
        _library = lib
    return _library


def _process_device() -> int:
    """This process's RTCDevice (a forked child makes its own: Embree's threads stay with the parent)."""
    global _device
    if _device is None or _device[0] != os.getpid():
        device = library().rtcNewDevice(None)
        if not device:
            raise RuntimeError("Embree could not create a device (unsupported CPU?)")
        _device = (os.getpid(), device)
    return _device[1]


class TriangleScene:
    """One triangle mesh as a committed Embree scene; ``handle`` is what the kernels take.

    Embree copies the vertices and faces into its own buffers, so the arrays may be dropped.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.uint32)
        lib, device = library(), _process_device()
        scene = lib.rtcNewScene(device)
        lib.rtcSetSceneFlags(scene, _SCENE_FLAG_ROBUST)
        geometry = lib.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
        # Embree's own buffers carry the padding its SIMD loads read past the last vertex.
        for kind, fmt, array in ((_BUFFER_TYPE_VERTEX, _FORMAT_FLOAT3, vertices), (_BUFFER_TYPE_INDEX, _FORMAT_UINT3, faces)):
            target = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, 12, len(array))
            if target:
                ctypes.memmove(target, array.ctypes.data, array.nbytes)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scene)
        error = lib.rtcGetDeviceError(device)
        self._release = weakref.finalize(self, lib.rtcReleaseScene, scene)
        if error:
            self._release()
            raise RuntimeError(f"Embree could not build the scene ({len(faces)} triangles): {_ERRORS.get(error, error)}")
        self.handle = int(scene)



def _call_query(name: str):
    """An intrinsic ``query(scene, record_address)`` calling Embree's ``name(scene, record, NULL)``."""

    @intrinsic
    def query(typingctx, scene, record):
        def codegen(context, builder, signature, args):
            byte_pointer = ir.IntType(8).as_pointer()
            function = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), [byte_pointer] * 3), _SYMBOL_PREFIX + name)
            builder.call(function, [builder.inttoptr(args[0], byte_pointer), builder.inttoptr(args[1], byte_pointer),
                                    ir.Constant(byte_pointer, None)])  # fmt: skip
            return context.get_dummy_value()

        return types.void(types.intp, types.intp), codegen

    return query


rtc_intersect1 = _call_query("rtcIntersect1")  # (scene, RTCRayHit address): the closest hit
rtc_occluded1 = _call_query("rtcOccluded1")  # (scene, RTCRay address): tfar = -inf when blocked


@numba.njit(cache=True, inline="always")
def ray_record():
    """A thread's scratch RTCRayHit: (float32 words, the same words as uint32, its address).
    Embree reads the ray with aligned vector loads, hence the 64-byte alignment."""
    raw = np.empty(RECORD_WORDS + 16, np.float32)
    skip = ((64 - (raw.ctypes.data & 63)) & 63) // 4
    words = raw[skip:skip + RECORD_WORDS]
    return words, words.view(np.uint32), words.ctypes.data
