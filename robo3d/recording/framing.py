"""MCAP framing: the files of a recording, their records, and where a damaged file breaks.

A recording is one ``.mcap`` file or a rosbag2 directory (``recording-format.md``,
Encodings). This module finds its files (:func:`bag_files`), walks each file record by
record (:func:`scan_file`) and reads an intact file's summary section
(:func:`read_summary`); it decodes no message. Message decoding is
:mod:`~robo3d.recording.decoding`, assembly and checks :mod:`~robo3d.recording.reader`.

References: the MCAP format specification (https://mcap.dev/spec: magic, the
``opcode u8, length u64, body`` record framing, chunks, the summary section and footer);
rosbag2's ``metadata.yaml`` and split bags (https://github.com/ros2/rosbag2).

Choices
-------
- A rosbag2 directory is ``metadata.yaml`` and the ``.mcap`` files it lists (a split
  bag), read in order as one recording. A directory without ``metadata.yaml`` (the
  recorder died before writing it) is read from its ``.mcap`` files in split order with
  a warning; files listed but missing are reported and skipped. rosbag2's own file or
  message compression and non-MCAP storage (``sqlite3``) are errors that say how to
  convert.
- The file is scanned record by record with robo3d's own framing loop (the record layout
  of the MCAP specification; ``mcap``'s record classes parse the rare records), so that
  damage is located to the byte:

  * a file that ends early (truncated, or whose framing breaks) is read up to the last
    intact record; a warning says how many bytes were lost, from which byte, and the log
    time of the last intact message (:attr:`Scan.truncated`; the reader's error says the
    file was truncated when what remains lacks a required role).
  * a chunk whose CRC does not match (or that does not decompress) is **skipped with a
    warning** naming its byte offset and log-time range (:attr:`Scan.damaged`). Skipping
    is robust because a chunk's framing (its length) is independent of its content, and
    the schemas and channels it may have carried are repeated in the summary section.
    Anything the lost messages leave missing is still caught by the reader: a role
    without messages, a pose gap wider than ``max_pose_gap`` at lookup. Decompression is
    streamed and bounded by the chunk's declared size, so a damaged size field cannot
    exhaust memory.
  * an attachment whose CRC does not match is skipped with a warning.
  * a message whose log time is beyond ``2**63`` ns (a damaged header) is skipped and
    counted; messages whose channel record is lost are counted and skipped.
"""

from __future__ import annotations

import io
import os
import re
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Metadata,
    MetadataIndex,
    Statistics,
)

from ..errors import RecordingError

__all__ = ["MAGIC", "MAX_STAMP", "Schema", "Channel", "Scan", "scan_file", "read_summary",
           "bag_files"]

#: The magic bytes an MCAP file starts and ends with.
MAGIC = b"\x89MCAP0\r\n"
#: The latest time a stamp or log time may have, nanoseconds (``2**63 - 1``).
MAX_STAMP = 2**63 - 1


# =========================================================================== scanning
class Schema(NamedTuple):
    """An MCAP schema record."""

    id: int
    name: str
    encoding: str
    data: bytes


class Channel(NamedTuple):
    """An MCAP channel record."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str


@dataclass
class Scan:
    """What a record-by-record pass over a file found (:func:`scan_file`), or its summary
    section (:func:`read_summary`: no messages, attachments without their bytes).

    ``messages`` are ``(channel id, log time, bytes)`` of the kept topics in file order;
    ``counts`` and ``log_times`` cover every channel. ``warnings`` says what was skipped
    or lost; ``truncated`` describes a file that ends early (None when intact) and
    ``damaged`` the records skipped as corrupt.
    """

    path: str
    size: int
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    # (channel id, log time, data) in file order, for the kept channels
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)  # messages per channel id
    log_times: dict[int, list[int]] = field(default_factory=dict)  # per channel, file order
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    truncated: str | None = None  # description of what was lost, if anything
    damaged: list[str] = field(default_factory=list)  # records skipped as corrupt
    data_end_seen: bool = False
    last_log_time: int | None = None


class _Corrupt(Exception):
    """A record whose framing is intact but whose content is not."""


def _str(mv: memoryview, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", mv, off)
    off += 4
    if off + n > len(mv):
        raise _Corrupt("string runs past the end of its record")
    return bytes(mv[off: off + n]).decode("utf-8"), off + n


def _parse_schema(mv: memoryview) -> Schema:
    (sid,) = struct.unpack_from("<H", mv, 0)
    name, off = _str(mv, 2)
    enc, off = _str(mv, off)
    (n,) = struct.unpack_from("<I", mv, off)
    off += 4
    if off + n > len(mv):
        raise _Corrupt("schema data runs past the end of its record")
    return Schema(sid, name, enc, bytes(mv[off: off + n]))


def _parse_channel(mv: memoryview) -> Channel:
    cid, sid = struct.unpack_from("<HH", mv, 0)
    topic, off = _str(mv, 4)
    enc, off = _str(mv, off)
    return Channel(cid, sid, topic, enc)


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


def _fmt_time(t: int | None) -> str:
    return "none" if t is None else f"{t} ns ({t / 1e9:.6f} s)"


class _Scanner:
    """Record-by-record reader of one MCAP file (the framing of the MCAP spec)."""

    def __init__(self, path: str, keep_topic: Callable[[str], bool],
                 keep_attachment_data: bool = True) -> None:
        self.keep_topic = keep_topic
        self.keep_attachment_data = keep_attachment_data
        self.scan = Scan(path=path, size=0)
        self._pending: list[tuple[int, int, bytes]] = []  # messages of not-yet-known channels
        self._n_messages = 0
        self._bad_log_times = 0

    # ------------------------------------------------------------------ records
    def _message(self, mv: memoryview) -> None:
        if len(mv) < 22:
            raise _Corrupt(f"message record of {len(mv)} bytes is shorter than its header")
        cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", mv, 0)
        s = self.scan
        if log_time > MAX_STAMP:  # a damaged header: no time can be that late
            self._bad_log_times += 1
            return
        s.counts[cid] = s.counts.get(cid, 0) + 1
        lt = s.log_times.get(cid)
        if lt is None:
            s.log_times[cid] = [log_time]
        else:
            lt.append(log_time)
        self._n_messages += 1
        if s.last_log_time is None or log_time > s.last_log_time:
            s.last_log_time = log_time
        ch = s.channels.get(cid)
        if ch is None:
            self._pending.append((cid, log_time, bytes(mv[22:])))
        elif self.keep_topic(ch.topic):
            s.messages.append((cid, log_time, bytes(mv[22:])))

    def _inner(self, opcode: int, mv: memoryview) -> None:
        if opcode == Opcode.MESSAGE:
            self._message(mv)
        elif opcode == Opcode.SCHEMA:
            sch = _parse_schema(mv)
            self.scan.schemas[sch.id] = sch
        elif opcode == Opcode.CHANNEL:
            ch = _parse_channel(mv)
            self.scan.channels[ch.id] = ch

    def _chunk(self, mv: memoryview, pos: int) -> None:
        start, end, usize, crc = struct.unpack_from("<QQQI", mv, 0)
        compression, off = _str(mv, 28)
        (n,) = struct.unpack_from("<Q", mv, off)
        off += 8
        if off + n > len(mv):
            raise _Corrupt("chunk data runs past the end of its record")
        raw = mv[off: off + n]
        where = f"chunk at byte {pos} (messages logged {start} .. {end} ns)"
        try:
            if compression == "zstd":
                data = _zstd_bounded(raw, usize)
            elif compression == "lz4":
                import lz4.frame

                data = lz4.frame.LZ4FrameDecompressor().decompress(bytes(raw),
                                                                    max_length=usize + 1)
            elif compression == "":
                data = bytes(raw)
            else:
                raise RecordingError(f"{where} uses compression {compression!r}, which this "
                                     f"reader does not support (zstd, lz4 or none)",
                                     path=self.scan.path)
        except ImportError as exc:
            raise RecordingError(f"{where} is {compression}-compressed and the module to "
                                 f"decompress it is missing ({exc}); pip install zstandard lz4",
                                 path=self.scan.path) from None
        except RecordingError:
            raise
        except Exception as exc:
            raise _Corrupt(f"{where} does not decompress ({type(exc).__name__}: {exc})") from None
        if len(data) != usize:
            raise _Corrupt(f"{where} decompresses to {len(data)} bytes, its header says {usize}")
        if crc != 0 and zlib.crc32(data) != crc:
            raise _Corrupt(f"{where} fails its CRC check (expected 0x{crc:08x}, "
                           f"got 0x{zlib.crc32(data):08x})")
        dmv = memoryview(data)
        o = 0
        records: list[tuple[int, memoryview]] = []
        while o < len(dmv):
            if o + 9 > len(dmv):
                raise _Corrupt(f"{where}: a record header runs past the end of the chunk")
            op, ln = struct.unpack_from("<BQ", dmv, o)
            if o + 9 + ln > len(dmv):
                raise _Corrupt(f"{where}: a {_opname(op)} record runs past the end of the chunk")
            records.append((op, dmv[o + 9: o + 9 + ln]))
            o += 9 + ln
        for op, rec in records:  # all-or-nothing: framing checked first
            self._inner(op, rec)

    def _attachment(self, body: bytes, pos: int) -> None:
        att = Attachment.read(_stream(body))
        (crc,) = struct.unpack_from("<I", body, len(body) - 4)
        if self.keep_attachment_data and crc != 0 and zlib.crc32(body[:-4]) != crc:
            raise _Corrupt(f"attachment {att.name!r} at byte {pos} fails its CRC check")
        self.scan.attachments[att.name] = att.data if self.keep_attachment_data else b""

    # ------------------------------------------------------------------ main loop
    def run(self) -> Scan:
        s = self.scan
        path = s.path
        try:
            s.size = os.path.getsize(path)
            f = open(path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise RecordingError(f"cannot open the recording: {exc.strerror or exc}",
                                 path=path) from None
        with f:
            magic = f.read(8)
            if magic != MAGIC:
                if magic and len(magic) < 8 and MAGIC.startswith(magic):
                    raise RecordingError(f"truncated: the file has only {len(magic)} bytes, "
                                         f"part of the MCAP magic", path=path)
                raise RecordingError(f"not an MCAP file (it starts with {magic!r}, an MCAP "
                                     f"file starts with {MAGIC!r})", path=path)
            pos = 8
            footer_seen = False
            while pos < s.size:
                hdr = f.read(9)
                if len(hdr) < 9:
                    self._truncated(pos, f"a record header needs 9 bytes, "
                                         f"{len(hdr)} remain")
                    break
                opcode, length = struct.unpack("<BQ", hdr)
                remain = s.size - pos - 9
                if length > remain:
                    self._truncated(pos, f"a {_opname(opcode)} record claims {length} bytes, "
                                         f"{remain} remain")
                    break
                body = f.read(length)
                try:
                    self._record(opcode, body, pos)
                except _Corrupt as exc:
                    self._warn(f"{exc}; skipped it (its content is lost)")
                    s.damaged.append(str(exc))
                except RecordingError:
                    raise
                except Exception as exc:  # struct/unicode/mcap errors of a damaged record
                    text = (f"the {_opname(opcode)} record at byte {pos} is corrupt "
                            f"({type(exc).__name__}: {exc})")
                    self._warn(f"{text}; skipped it")
                    s.damaged.append(text)
                pos += 9 + length
                if opcode == Opcode.FOOTER:
                    footer_seen = True
                    tail = f.read(8)
                    if tail != MAGIC:
                        self._warn("the file ends without the closing MCAP magic after its "
                                   "footer (truncated in the last bytes; no data lost)")
                    break
            else:
                if not footer_seen:
                    self._truncated(pos, "the file ends before its footer")
        # messages whose channel record came later (or only in the summary section)
        for cid, log_time, data in self._pending:
            ch = s.channels.get(cid)
            if ch is not None and self.keep_topic(ch.topic):
                s.messages.append((cid, log_time, data))
        if self._bad_log_times:
            text = (f"{self._bad_log_times} messages have a log time beyond 2**63 ns (damaged "
                    f"message headers); skipped them")
            self._warn(text)
            s.damaged.append(text)
        lost = sorted({cid for cid, _, _ in self._pending if cid not in s.channels})
        if lost:
            n = sum(1 for cid, _, _ in self._pending if cid not in s.channels)
            self._warn(f"{n} messages on channel ids {lost} have no channel record "
                       f"(lost with a damaged chunk or summary); skipped them")
        return s

    def _record(self, opcode: int, body: bytes, pos: int) -> None:
        s = self.scan
        if opcode == Opcode.CHUNK:
            self._chunk(memoryview(body), pos)
        elif opcode in (Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL):
            self._inner(opcode, memoryview(body))
        elif opcode == Opcode.METADATA:
            md = Metadata.read(_stream(body))
            s.metadata.setdefault(md.name, {}).update(md.metadata)
        elif opcode == Opcode.ATTACHMENT:
            self._attachment(body, pos)
        elif opcode == Opcode.DATA_END:
            s.data_end_seen = True

    def _warn(self, text: str) -> None:
        self.scan.warnings.append(text)

    def _truncated(self, pos: int, what: str) -> None:
        s = self.scan
        lost = s.size - pos
        if s.data_end_seen:
            text = (f"the file is truncated in its summary section at byte {pos} of {s.size} "
                    f"({what}); every message is intact")
            self._warn(text)
            return
        text = (f"the file is truncated or damaged at byte {pos} of {s.size} ({what}): its "
                f"last {lost} bytes are unusable and at least one record and the summary "
                f"section are lost; read {self._n_messages} intact messages, the last logged "
                f"at {_fmt_time(s.last_log_time)}")
        s.truncated = text
        self._warn(text)


def _zstd_bounded(raw: memoryview, usize: int) -> bytes:
    """Decompress one zstd frame, never producing more than ``usize + 1`` bytes (a damaged
    size field or frame header must not allocate gigabytes)."""
    import zstandard

    reader = zstandard.ZstdDecompressor().stream_reader(bytes(raw))
    parts, total = [], 0
    while total <= usize:
        piece = reader.read(min(1 << 24, usize + 1 - total))
        if not piece:
            break
        parts.append(piece)
        total += len(piece)
    return b"".join(parts)


def _stream(body: bytes) -> Any:
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(body))


def scan_file(path: str, keep_topic: Callable[[str], bool],
              keep_attachment_data: bool = True) -> Scan:
    """Walk one MCAP file record by record (see the module docstring for damage).

    Parameters
    ----------
    path : str
    keep_topic : callable
        Whether to keep the messages of a topic (their bytes go to :attr:`Scan.messages`;
        every topic's messages are counted either way).
    keep_attachment_data : bool
        Keep attachments' bytes (and check their CRCs), or only their names.

    Returns
    -------
    Scan

    Raises
    ------
    RecordingError
        The file cannot be opened, is not MCAP (or only part of its magic), or has a
        chunk compressed with an unsupported or unavailable codec.
    """
    return _Scanner(path, keep_topic, keep_attachment_data).run()


# =========================================================================== files
def bag_files(path: str | os.PathLike[str]) -> tuple[list[str], list[str]]:
    """The MCAP files of a recording, in order, and warnings about the set.

    Parameters
    ----------
    path : str or path-like
        An ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` and its ``.mcap``
        files; without ``metadata.yaml``, every ``.mcap`` in it in split order).

    Returns
    -------
    files : list of str
    warnings : list of str
        Files listed in ``metadata.yaml`` but missing, a missing or unreadable
        ``metadata.yaml``, ``.mcap`` files present but not listed.

    Raises
    ------
    RecordingError
        No such file or directory; a directory without ``.mcap`` files; a bag with
        another storage (``sqlite3``) or with rosbag2's own compression.
    """
    spath = os.fspath(path)
    if os.path.isfile(spath):
        return [spath], []
    if not os.path.isdir(spath):
        raise RecordingError("no such file or directory", path=spath)
    warnings: list[str] = []
    present = sorted((f for f in os.listdir(spath) if f.endswith(".mcap")), key=_split_key)
    meta_path = os.path.join(spath, "metadata.yaml")
    info = None
    if os.path.isfile(meta_path):
        try:
            import yaml

            with open(meta_path, encoding="utf-8") as f:
                doc = yaml.safe_load(f)
            info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
            if not isinstance(info, dict):
                raise ValueError("no rosbag2_bagfile_information mapping")
        except Exception as exc:  # yaml errors, bad structure: fall back to the files
            warnings.append(f"metadata.yaml is unreadable ({type(exc).__name__}: {exc}); "
                            f"read the .mcap files in split order")
            info = None
    elif present:
        warnings.append("the rosbag2 directory has no metadata.yaml (the recorder did not "
                        "finish); read its .mcap files in split order")
    if info is not None:
        storage = str(info.get("storage_identifier", "mcap") or "mcap")
        if storage != "mcap":
            raise RecordingError(f"rosbag2 storage {storage!r} is not supported: robo3d reads "
                                 f"MCAP bags (convert with `ros2 bag convert` to "
                                 f"storage_id mcap)", path=spath)
        mode = str(info.get("compression_mode", "") or "")
        if mode:
            fmt = info.get("compression_format", "")
            raise RecordingError(f"rosbag2 compression (mode {mode!r}, format {fmt!r}) is not "
                                 f"supported: record with MCAP's own chunk compression "
                                 f"(`ros2 bag record -s mcap --storage-preset-profile "
                                 f"zstd_fast`), or decompress the files first "
                                 f"(`zstd -d`, then fix metadata.yaml)", path=spath)
        listed = [str(p) for p in (info.get("relative_file_paths") or [])]
        files = []
        for rel in listed:
            full = os.path.join(spath, rel)
            if os.path.isfile(full):
                files.append(full)
            else:
                warnings.append(f"{rel} is listed in metadata.yaml but missing; its "
                                f"messages are lost")
        extra = [f for f in present if os.path.join(spath, f) not in files]
        if extra:
            warnings.append(f"{', '.join(extra)} not listed in metadata.yaml; read too")
            files += [os.path.join(spath, f) for f in extra]
    else:
        files = [os.path.join(spath, f) for f in present]
    if not files:
        raise RecordingError("a directory without .mcap files (a recording is an .mcap file "
                             "or a rosbag2 directory with metadata.yaml and .mcap files)",
                             path=spath)
    return files, warnings


def _split_key(name: str) -> tuple[str, int]:
    """Split bags number their files ``<bag>_0.mcap``, ``<bag>_1.mcap``, ... ``_10``."""
    m = re.match(r"^(.*?)(\d+)\.mcap$", name)
    return (m.group(1), int(m.group(2))) if m else (name, -1)


# =========================================================================== summary
def read_summary(path: str) -> Scan | None:
    """The summary section of an intact file as a :class:`Scan` without messages, or None
    when the file has no usable summary (no statistics, or anything amiss)."""
    size = os.path.getsize(path)
    footer_len = 1 + 8 + 20
    if size < 8 + footer_len + 8:
        return None
    with open(path, "rb") as f:
        f.seek(size - 8 - footer_len)
        tail = f.read(footer_len + 8)
        if tail[-8:] != MAGIC or tail[0] != Opcode.FOOTER:
            return None
        summary_start, _offsets, _crc = struct.unpack_from("<QQI", tail, 9)
        if summary_start == 0 or summary_start >= size - 8 - footer_len:
            return None
        f.seek(summary_start)
        body = f.read(size - 8 - footer_len - summary_start)
        scan = Scan(path=path, size=size)
        stats = None
        md_index: list[MetadataIndex] = []
        o = 0
        mv = memoryview(body)
        while o < len(body):
            op, ln = struct.unpack_from("<BQ", body, o)
            if o + 9 + ln > len(body):
                return None
            rec = bytes(mv[o + 9: o + 9 + ln])
            if op == Opcode.SCHEMA:
                s = _parse_schema(memoryview(rec))
                scan.schemas[s.id] = s
            elif op == Opcode.CHANNEL:
                c = _parse_channel(memoryview(rec))
                scan.channels[c.id] = c
            elif op == Opcode.STATISTICS:
                stats = Statistics.read(_stream(rec))
            elif op == Opcode.ATTACHMENT_INDEX:
                ai = AttachmentIndex.read(_stream(rec))
                scan.attachments[ai.name] = b""
            elif op == Opcode.METADATA_INDEX:
                md_index.append(MetadataIndex.read(_stream(rec)))
            o += 9 + ln
        if stats is None:
            return None
        scan.counts = dict(stats.channel_message_counts)
        for mi in md_index:
            f.seek(mi.offset)
            hdr = f.read(9)
            op, ln = struct.unpack("<BQ", hdr)
            if op != Opcode.METADATA:
                return None
            md = Metadata.read(_stream(f.read(ln)))
            scan.metadata.setdefault(md.name, {}).update(md.metadata)
        return scan
