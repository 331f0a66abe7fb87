"""One camera's MP4 files: the watched encoder that appends episodes, and the sequential decoder that hands
them back episode by episode."""
from __future__ import annotations

import threading
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import av
import numpy as np

from jepa_envs.datasets.lerobot.format import (CODECS, ENCODER_TIMEOUT_S, TOLERANCE_S, VIDEO_FILE_MB, VIDEO_PATH,
                                               LeRobotError, next_file)


class VideoWriter:
    """One camera's video files: episodes appended one after the other, a new file past VIDEO_FILE_MB.

    The encoder runs on a watched thread: one that takes no frame and hands back no packet for ``timeout_s``
    has stalled (a C library call cannot be interrupted), and the export stops with the episode and the fix
    instead of waiting for good."""

    def __init__(self, root: Path, key: str, fps: int, codec: str, height: int, width: int,
                 timeout_s: float = ENCODER_TIMEOUT_S):
        self.root, self.key, self.fps, self.codec = root, key, fps, codec
        self.height, self.width = height, width
        self.timeout_s = timeout_s
        self.chunk = self.file = 0
        self.container = None
        self.frames = 0          # frames in the current file
        self.bytes = 0           # bytes muxed into it (the encoder may hold frames back: not the file's size yet)
        self.progress = 0        # frames sent and packets muxed, ever: what the watch looks at
        self.stalled = False
        self.episode = -1        # the episode being encoded (or the last one, while flushing)
        self.last_dts: int | None = None

    def _open(self) -> None:
        encoder, pix_fmt, options = CODECS[self.codec]
        path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.chunk, file_index=self.file)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.container = av.open(str(path), "w")
        self.stream = self.container.add_stream(encoder, rate=self.fps)
        self.stream.width, self.stream.height, self.stream.pix_fmt = self.width, self.height, pix_fmt
        self.stream.time_base = Fraction(1, self.fps)
        self.stream.options = dict(options)
        self.frames = self.bytes = 0
        self.last_dts = None

    def add_episode(self, frames: np.ndarray, episode: int) -> dict:
        """Encode one episode's (T, H, W, 3) uint8 frames; returns its LeRobot episode columns."""
        if self.container is not None and self.bytes / 2**20 >= VIDEO_FILE_MB:
            self.close()
            self.chunk, self.file = next_file(self.chunk, self.file)
        if self.container is None:
            self._open()
        start = self.frames
        self.episode = episode
        self._watched(lambda: self._encode(frames), f"encoding episode {episode}")
        return {f"videos/{self.key}/chunk_index": self.chunk, f"videos/{self.key}/file_index": self.file,
                f"videos/{self.key}/from_timestamp": start / self.fps,
                f"videos/{self.key}/to_timestamp": self.frames / self.fps}

    def _encode(self, frames: np.ndarray) -> None:
        for frame in frames:
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            vf.pts, vf.time_base = self.frames, Fraction(1, self.fps)
            self.frames += 1
            self.progress += 1
            for packet in self.stream.encode(vf):
                self._mux(packet)

    def _mux(self, packet) -> None:
        if self.last_dts is not None and packet.dts is not None and packet.dts <= self.last_dts:
            raise LeRobotError(f"the {CODECS[self.codec][0]} encoder of {self.key} handed out frame {packet.dts} "
                               f"after frame {self.last_dts} (episode {self.episode}); packets out of decoding order "
                               "cannot be stored: export again, or with --codec lossless or h264")
        self.last_dts = packet.dts
        self.bytes += packet.size
        self.progress += 1
        self.container.mux(packet)

    def _watched(self, job, what: str) -> None:
        """Run ``job`` on a daemon thread; raise (leaving the thread behind) if it makes no progress for
        ``timeout_s``, and re-raise what it raised."""
        failure: list[BaseException] = []

        def run() -> None:
            try:
                job()
            except BaseException as exc:   # handed to the caller's thread below
                failure.append(exc)

        thread = threading.Thread(target=run, name=f"encoder {self.key}", daemon=True)
        seen = self.progress
        thread.start()
        while True:
            thread.join(self.timeout_s)
            if not thread.is_alive():
                break
            if self.progress == seen:
                self.stalled = True
                raise LeRobotError(f"the {CODECS[self.codec][0]} encoder of {self.key} made no progress for "
                                   f"{self.timeout_s:g} s while {what}; it has stalled (nothing was written): "
                                   f"export again, or with --codec lossless or h264 (or a longer "
                                   f"--encoder-timeout when frames are large)")
            seen = self.progress
        if failure:
            raise failure[0]

    def close(self) -> None:
        """Flush the encoder (the frames it still holds) and close the current file."""
        if self.container is not None:
            self._watched(self._flush, f"flushing the frames it held after episode {self.episode}")
            self.container.close()
            self.container = None

    def _flush(self) -> None:
        for packet in self.stream.encode():
            self._mux(packet)

    def discard(self) -> None:
        """Give up the current file without flushing (the export failed); a stalled encoder is left alone."""
        if self.container is not None and not self.stalled:
            self.container.close()
        self.container = None

    def info(self) -> dict:
        """The feature's ``info`` as LeRobot's ``get_video_info`` reads it from the file."""
        path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=0, file_index=0)
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            return {"video.height": stream.height, "video.width": stream.width,
                    "video.codec": stream.codec_context.codec.canonical_name, "video.pix_fmt": stream.pix_fmt,
                    "video.is_depth_map": False, "video.fps": self.fps, "video.channels": 3, "has_audio": False}



class VideoReader:
    """Frames of a camera's video files in time order, handed out episode by episode (sequential decode)."""

    def __init__(self, root: Path, key: str):
        self.root, self.key = root, key
        self.open_path: Path | None = None
        self.frames: Iterator | None = None
        self.pending: tuple[float, np.ndarray] | None = None

    def _file(self, chunk: int, file: int) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=chunk, file_index=file)

    def episode(self, chunk: int, file: int, start: float, end: float, length: int, episode: int) -> np.ndarray:
        path = self._file(chunk, file)
        rel = path.relative_to(self.root)
        if path != self.open_path:
            if not path.is_file():
                raise LeRobotError(f"{rel} is missing (episode {episode} of {self.key} lies in it); download the "
                                   "dataset's videos folder whole")
            try:
                container = av.open(str(path))
                stream = container.streams.video[0]
            except (av.error.FFmpegError, IndexError) as exc:
                raise LeRobotError(f"{rel} is not a readable video ({exc}); re-download or re-encode it") from None
            stream.thread_type = "AUTO"

            def frames(container=container, stream=stream):
                try:
                    for frame in container.decode(stream):
                        yield float(frame.pts * stream.time_base), frame.to_ndarray(format="rgb24")
                except av.error.FFmpegError as exc:
                    raise LeRobotError(f"{rel} is damaged ({exc}); re-download or re-encode it") from None
                finally:
                    container.close()
            self.open_path, self.frames, self.pending = path, frames(), None
        out = []
        while len(out) < length:
            item = self.pending if self.pending is not None else next(self.frames, None)
            self.pending = None
            if item is None or item[0] >= end - TOLERANCE_S:
                self.pending = item
                raise LeRobotError(f"{rel} holds {len(out)} frames of episode {episode} ({start:.3f} s to "
                                   f"{end:.3f} s) but the episode has {length} rows; the video is shorter than "
                                   "its episode: re-encode it from the episode's frames")
            if item[0] >= start - TOLERANCE_S:
                out.append(item[1])
        return np.stack(out)
