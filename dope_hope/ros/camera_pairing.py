"""The camera of each image of a ROS stream: ``image_transport``'s rule (a
``CameraSubscriber`` pairs an image with the ``CameraInfo`` whose header stamp equals the
image's), as one small class that a recording reader and a live node can both hold.

:class:`CameraByStamp` collects the ``CameraInfo`` messages by stamp (equal messages kept as
one camera, so a recording of one camera parses its info once) and gives each image its
camera: the one of the image's own stamp; else, when the stream has only one camera (a
driver that stamps its info apart from its images), that one; else a
:class:`~dope_hope.errors.CameraError` naming the stamp, because the camera changes within
the stream and no info says which one the image was taken with. It also holds the one rule
of a camera that states no image size: every image it is paired with has the size of the
first (a K is the K of one image size).
"""
from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from dope_hope.errors import CameraError

Camera = TypeVar("Camera")


class CameraByStamp(Generic[Camera]):
    """The cameras of a stream by their header stamps (module docstring).

    Args:
        where: the stream's camera_info source (file and topic), for messages.
    """

    def __init__(self, where: str):
        self.where = where
        self._key_by_stamp: dict[int, Hashable] = {}
        self._cameras: dict[Hashable, Camera] = {}
        self._first_size: dict[Hashable, tuple[int, int, str]] = {}

    def add(self, stamp_ns: int, key: Hashable, make: Callable[[], Camera]) -> None:
        """Record the camera of ``stamp_ns``: ``key`` identifies its message's content (equal
        contents, one camera); ``make()`` builds the camera the first time a key is seen. A
        later message of the same stamp replaces an earlier one."""
        if key not in self._cameras:
            self._cameras[key] = make()
        self._key_by_stamp[int(stamp_ns)] = key

    def __len__(self) -> int:
        """The number of different cameras recorded."""
        return len(self._cameras)

    def _key_for(self, stamp_ns: int) -> Hashable:
        key = self._key_by_stamp.get(int(stamp_ns))
        if key is not None:
            return key
        if len(self._cameras) == 1:
            return next(iter(self._cameras))
        if not self._cameras:
            raise CameraError(f"{self.where}: holds no CameraInfo message; give --camera")
        raise CameraError(f"{self.where}: no CameraInfo stamped {stamp_ns / 1e9:.9f} s, the stamp of an image, "
                          f"and the camera changes within the recording ({len(self._cameras)} different ones): "
                          "which one took the image is unknown (image_transport pairs equal stamps); give --camera")

    def camera_for(self, stamp_ns: int) -> Camera:
        """The camera of the image stamped ``stamp_ns`` (module docstring); CameraError when
        the stream cannot say."""
        return self._cameras[self._key_for(stamp_ns)]

    def check_image_size(self, stamp_ns: int, width: int, height: int, image: str,
                         stated: tuple[int, int] | None) -> None:
        """CameraError when the camera of ``stamp_ns`` states no size (``stated`` None) and
        ``image`` (its name, for the message) has another size than the first image paired
        with it: its K would be applied to pixels of another scale."""
        if stated is not None:
            return
        key = self._key_for(stamp_ns)
        first = self._first_size.setdefault(key, (int(width), int(height), image))
        if first[:2] != (int(width), int(height)):
            raise CameraError(f"{self.where}: the camera states no image size and {image} is {width}x{height}, "
                              f"the image {first[2]} {first[0]}x{first[1]}: a K is the K of one size "
                              "(record camera_info with its width and height, or give --camera)")


def single_camera(where: str, camera: Camera) -> CameraByStamp[Camera]:
    """A :class:`CameraByStamp` of one camera for every stamp (a camera the caller gives)."""
    pairing: CameraByStamp[Camera] = CameraByStamp(where)
    pairing.add(0, "given", lambda: camera)
    return pairing
