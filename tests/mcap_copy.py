"""A recording copied record by record with mcap's own reader and writer (not robo3d's),
its metadata and attachments kept, changed or left out: recordings as other writers
make them (a ROS bag carries neither box nor ground truth)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def copy_recording(src: Path, dst: Path, *,
                   metadata: Callable[[str, dict[str, str]], dict[str, str] | None] | None
                   = lambda name, md: md,
                   attachments: bool = True,
                   keep: Callable[[str, bytes], bool] | None = None,
                   message: Callable[[str, str, bytes], bytes] | None = None,
                   attachment: Callable[[str, bytes], bytes] | None = None) -> Path:
    """Copy ``src`` to ``dst``: every channel and message (those for which ``keep(topic,
    data)`` is true, when given), its data as ``message(schema_name, message_encoding,
    data)`` returns it (when given); each metadata record as ``metadata(name, record)``
    returns it (None leaves it out; ``metadata=None`` leaves all out); the attachments
    when ``attachments``, each one's data as ``attachment(name, data)`` returns it."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        r = make_reader(f)
        w = Writer(g)
        w.start()
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for sch, ch, m in r.iter_messages(log_time_order=False):
            if keep is not None and not keep(ch.topic, m.data):
                continue
            if sch.id not in sids:
                sids[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in cids:
                cids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sids[sch.id])
            data = m.data if message is None else message(sch.name, ch.message_encoding,
                                                          m.data)
            w.add_message(cids[ch.id], log_time=m.log_time, data=data,
                          publish_time=m.publish_time)
        if metadata is not None:
            for md in r.iter_metadata():
                kept = metadata(md.name, dict(md.metadata))
                if kept is not None:
                    w.add_metadata(md.name, kept)
        if attachments:
            for a in r.iter_attachments():
                data = a.data if attachment is None else attachment(a.name, a.data)
                w.add_attachment(create_time=a.create_time, log_time=a.log_time,
                                 name=a.name, media_type=a.media_type, data=data)
        w.finish()
    return dst
