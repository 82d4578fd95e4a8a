"""Pictures in: image files and videos decoded, lens distortion removed, images resized.

Libraries: Pillow decodes image files (as the rest of physavatar does); OpenCV's FFmpeg backend
(``cv2.VideoCapture``) decodes videos, because it also reports the frame count the container
declares, so a truncated file is caught (decoded < declared); OpenCV removes lens distortion
(``cv2.initUndistortRectifyMap`` + ``cv2.remap``, ``cv2.fisheye`` for the fisheye model) and
resizes (``cv2.resize``: area averaging when shrinking), both with the pixel-centre convention of
:mod:`physavatar.camera`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PhysavatarError
from .common import SourceCamera, log


def read_image(path: Path, mode: str = "RGB") -> np.ndarray:
    """[H, W, 3] (``RGB``) or [H, W] (``L``) uint8."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
            if mode == "L" and im.mode in ("RGBA", "LA"):
                return np.asarray(im.getchannel("A"), np.uint8)
            return np.asarray(im.convert(mode), np.uint8)
    except FileNotFoundError:
        raise PhysavatarError(path, "file not found") from None
    except Exception as e:
        raise PhysavatarError(path, f"unreadable or corrupt image ({type(e).__name__})") from None


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except Exception as e:
        raise PhysavatarError(path, f"unreadable or corrupt image ({type(e).__name__})") from None


@dataclass
class VideoInfo:
    width: int
    height: int
    fps: float
    frames: int  # as the container declares it (0: unknown)


def _open(path: Path):
    import cv2

    if not path.is_file():
        raise PhysavatarError(path, "video file not found")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise PhysavatarError(path, "cannot be opened as a video (corrupt, truncated or an unsupported codec)")
    return cap


def video_info(path: Path) -> VideoInfo:
    import cv2

    cap = _open(path)
    try:
        ok, frame = cap.read()
        if not ok:
            raise PhysavatarError(path, "video has no decodable frame (corrupt or truncated)")
        h, w = frame.shape[:2]
        return VideoInfo(w, h, float(cap.get(cv2.CAP_PROP_FPS) or 0.0), int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0))
    finally:
        cap.release()


class VideoFrames:
    """The frames of a video that ``keep(index)`` accepts, [H, W, 3] RGB uint8, as (index, frame) in order.

    Every frame is decoded (``grab``) to count them, but only kept ones are converted to RGB
    (``retrieve``). ``count`` is the number of decoded frames once iterated. Raises
    PhysavatarError when the file does not open, or when fewer frames decode than the container
    declares (a truncated or damaged file; 1 % slack for containers whose count is estimated
    from the duration).
    """

    def __init__(self, path: Path, keep=None):
        self.path, self.keep, self.count = path, keep, 0

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        import cv2

        cap = _open(self.path)
        declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        n = 0
        try:
            while cap.grab():
                n += 1
                self.count = n
                if self.keep is None or self.keep(n - 1):
                    ok, frame = cap.retrieve()
                    if not ok:
                        raise PhysavatarError(self.path, f"frame {n - 1} cannot be decoded (corrupt video)")
                    yield n - 1, np.ascontiguousarray(frame[..., ::-1])
        finally:
            cap.release()
        if n == 0:
            raise PhysavatarError(self.path, "video has no decodable frame (corrupt or truncated)")
        if declared > 0 and n < declared - max(1, int(0.01 * declared)):
            raise PhysavatarError(self.path, f"only {n} of the {declared} frames the file declares could be decoded "
                                             "(truncated or corrupt video)")


def fit_to_image(cam: SourceCamera, width: int, height: int, where: Path) -> SourceCamera:
    """The camera for pictures of ``width`` x ``height`` when the calibration is for another size.

    Same aspect (within a pixel): a downscaled or upscaled copy of the calibrated picture, K
    scaled about pixel corners. Smaller by at most 2 % in each direction (an encoder crop, e.g.
    1088 -> 1080): cropped at the right and bottom, K unchanged. Anything else is an error.
    """
    if (width, height) == (cam.width, cam.height):
        return cam
    sx, sy = width / cam.width, height / cam.height
    if abs(width - cam.width * sy) <= 1.0 and abs(height - cam.height * sx) <= 1.0:
        K = cam.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        if abs(sx - 1) > 1e-9:
            log.info("%s: camera %r calibrated at %dx%d, pictures are %dx%d: intrinsics scaled by %.4g",
                     where, cam.name, cam.width, cam.height, width, height, sx)
        return SourceCamera(cam.name, width, height, K, cam.w2c, cam.dist, cam.fisheye)
    if cam.width * 0.98 <= width <= cam.width and cam.height * 0.98 <= height <= cam.height:
        log.warning("%s: camera %r is calibrated for %dx%d but its pictures are %dx%d: taken as cropped at "
                    "the right and bottom (intrinsics unchanged)", where, cam.name, cam.width, cam.height, width, height)
        return SourceCamera(cam.name, width, height, cam.K, cam.w2c, cam.dist, cam.fisheye)
    raise PhysavatarError(where, f"pictures of camera {cam.name!r} are {width}x{height} but its calibration is for "
                                 f"{cam.width}x{cam.height} (neither a rescale nor a small crop)")


class Undistorter:
    """Removes lens distortion keeping K: an undistorted pixel (u, v) shows the ray K⁻¹(u, v, 1).

    Pixels whose ray falls outside the source picture become black (and 0 in masks).
    """

    def __init__(self, cam: SourceCamera):
        import cv2

        self.active = cam.distorted
        if not self.active:
            return
        size = (cam.width, cam.height)
        d = np.asarray(cam.dist, np.float64).reshape(-1)
        if cam.fisheye:
            self.map1, self.map2 = cv2.fisheye.initUndistortRectifyMap(cam.K, d[:4], np.eye(3), cam.K, size, cv2.CV_32FC1)
        else:
            self.map1, self.map2 = cv2.initUndistortRectifyMap(cam.K, d, None, cam.K, size, cv2.CV_32FC1)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        import cv2

        if not self.active:
            return image
        return cv2.remap(image, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def target_size(width: int, height: int, resolution) -> tuple[int, int]:
    if resolution is None:
        return width, height
    if isinstance(resolution, tuple):
        return resolution
    return max(1, int(round(width * resolution))), max(1, int(round(height * resolution)))


def resized_K(K: np.ndarray, size: tuple[int, int], new: tuple[int, int]) -> np.ndarray:
    """K for the picture resized from ``size`` to ``new`` (pixel centres at integers: scale about corners)."""
    sx, sy = new[0] / size[0], new[1] / size[1]
    K = np.array(K, np.float64)
    K[0, 0] *= sx
    K[0, 1] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def resize(image: np.ndarray, new: tuple[int, int]) -> np.ndarray:
    import cv2

    h, w = image.shape[:2]
    if (w, h) == tuple(new):
        return image
    interp = cv2.INTER_AREA if new[0] <= w and new[1] <= h else cv2.INTER_LINEAR
    return cv2.resize(image, tuple(int(x) for x in new), interpolation=interp)
