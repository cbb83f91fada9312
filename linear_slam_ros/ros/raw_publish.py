"""Publish an already serialised message through rcl, without holding the interpreter lock.

rclpy's ``Publisher.publish`` converts the message to C and serialises it with the lock held
(121 ms for a 72 MB ``global_map``, README "Scale"), and its ``publish(bytes)`` copies the bytes
into a ``std::string`` first, also with the lock held. :func:`publish_serialized` hands a
serialised message (:func:`msg_adapters.cdr.to_cdr`) to rcl's public
``rcl_publish_serialized_message`` through ``ctypes``, which releases the lock around the call:
the middleware makes its own copy, and the node's other threads run meanwhile. Same library
rclpy calls, same publisher (its handle is held for the call, so it cannot be destroyed
under it), the same message on the wire.

Where ``librcl`` or the publisher's address cannot be found (an rclpy other than Jazzy's), it
falls back to rclpy's ``publish(bytes)``: the same message, with the lock held.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
from typing import Any

import numpy as np
import numpy.typing as npt

from linear_slam_ros.core.errors import LinearSlamError

log = logging.getLogger(__name__)

RCL_RET_OK = 0


class PublishError(LinearSlamError):
    """rcl refused to publish a serialised message."""


class _Allocator(ctypes.Structure):
    """``rcutils_allocator_t``."""

    _fields_ = [
        ("allocate", ctypes.c_void_p),
        ("deallocate", ctypes.c_void_p),
        ("reallocate", ctypes.c_void_p),
        ("zero_allocate", ctypes.c_void_p),
        ("state", ctypes.c_void_p),
    ]


class _SerializedMessage(ctypes.Structure):
    """``rcl_serialized_message_t`` (``rcutils_uint8_array_t``)."""

    _fields_ = [
        ("buffer", ctypes.c_void_p),
        ("buffer_length", ctypes.c_size_t),
        ("buffer_capacity", ctypes.c_size_t),
        ("allocator", _Allocator),
    ]


class _ErrorString(ctypes.Structure):
    """``rcutils_error_string_t``."""

    _fields_ = [("str", ctypes.c_char * 1024)]


def _loaded_library(name: str) -> str | None:
    """Return the path of shared library ``name`` (e.g. ``librcl.so``) as this process mapped it."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            for line in maps:
                path = line.rstrip("\n").split(maxsplit=5)[-1]
                if path.rsplit("/", 1)[-1] == name:
                    return path
    except OSError:  # pragma: no cover - no /proc
        pass
    return ctypes.util.find_library(name.removeprefix("lib").removesuffix(".so"))


@functools.cache
def _rcl() -> tuple[Any, Any] | None:
    """Return ``(rcl_publish_serialized_message, rcutils error API)`` from the loaded rcl, or None."""
    paths = [_loaded_library("librcl.so"), _loaded_library("librcutils.so")]
    if None in paths:
        log.info("librcl not found: serialised messages go through rclpy's publish(bytes)")
        return None
    try:
        rcl, rcutils = ctypes.CDLL(paths[0]), ctypes.CDLL(paths[1])
        publish = rcl.rcl_publish_serialized_message
        default_allocator = rcutils.rcutils_get_default_allocator
        error_string = rcutils.rcutils_get_error_string
        reset_error = rcutils.rcutils_reset_error
    except (OSError, AttributeError) as exc:
        log.info("librcl not usable (%s): serialised messages go through rclpy's publish(bytes)", exc)
        return None
    publish.argtypes = [ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p]
    publish.restype = ctypes.c_int
    default_allocator.argtypes = []
    default_allocator.restype = _Allocator
    error_string.argtypes = []
    error_string.restype = _ErrorString
    reset_error.argtypes = []
    reset_error.restype = None
    return publish, (default_allocator, error_string, reset_error)


def publish_serialized(publisher: Any, buffer: npt.NDArray[np.uint8]) -> None:
    """Publish a serialised message (CDR with its encapsulation header) on an rclpy publisher.

    Args:
        publisher: an ``rclpy.publisher.Publisher`` of the message's type.
        buffer: the serialised message, contiguous, shape ``(bytes,)``; read during the call only.

    Raises:
        PublishError: rcl refused the message (its error string is in the message).
    """
    api = _rcl()
    handle = publisher.handle
    if api is None or not hasattr(handle, "pointer"):
        publisher.publish(np.ascontiguousarray(buffer).tobytes())
        return
    publish, (default_allocator, error_string, reset_error) = api
    data = np.ascontiguousarray(buffer, dtype=np.uint8)
    message = _SerializedMessage(data.ctypes.data, data.size, data.size, default_allocator())
    with handle:  # the publisher cannot be destroyed during the call
        ret = publish(handle.pointer, ctypes.byref(message), None)
    if ret != RCL_RET_OK:
        reason = error_string().str.decode(errors="replace")
        reset_error()
        raise PublishError(f"rcl_publish_serialized_message on {publisher.topic_name} returned {ret}: {reason}")
