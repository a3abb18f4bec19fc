"""The one bag reader: a ROS 2 bag (an .mcap file, or a rosbag2 directory of .mcap files read
in order) streamed in one pass with CRC checks, topic types, message counts, attachments and
metadata; damaged or truncated files raise :class:`BagError` with one clear line, or with
``salvage`` are read up to the damage. ``starleth-analyze`` (its ``analysis_run.Run``),
``starleth-view`` and ``starleth-demo`` read bags through :func:`stream_bag` /
:func:`read_messages`.

What the file claims never sizes an allocation, and what it holds is bounded before it is
read: a record's length by the file's size and by MAX_RECORD_BYTES; a compressed chunk's
uncompressed size (as its header declares it, and as its data decompresses, in pieces) by
its header and by MAX_RECORD_BYTES, checked before anything is decompressed; the metadata
and attachments kept by MAX_KEPT_BYTES in all (what is beyond is left out with a warning);
a message whose log or publish time is beyond int64 is counted as unreadable. YAML from a
bag is read by :func:`~starleth_interface.yaml_files.load_yaml_text` (bounded in size and in
what its aliases expand to)."""
from __future__ import annotations

import functools
import glob
import io
import os
import re
import sys
import zlib

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from ...ros.recording.mcap_sink import MCAP_MAGIC

#: log and publish times are int64 nanoseconds in ROS 2 (rcutils_time_point_value_t); an
#: MCAP Message record holds a uint64: one beyond the int64 range is damage
MAX_TIME_NS = 2 ** 63 - 1
#: a compressed chunk is decompressed in pieces of this size, so that what is held is what
#: the chunk's data decompresses to, never the size its header (or the frame's) claims
DECOMPRESS_PIECE = 1 << 20
#: the largest record read, and the largest chunk decompressed (its declared and its actual
#: size) [bytes]: 256 times the recorder's chunks (recording.DEFAULT_CHUNK_SIZE), more than
#: its largest message (a heightfield's configuration, 11 MiB); a zstd chunk of 98 KB that
#: truthfully declares 3 GiB is refused before it is decompressed
MAX_RECORD_BYTES = 64 * 1024 * 1024
#: the metadata and attachments kept from a bag, in all [bytes]: a bag of sim_node holds a
#: few hundred kB of them (up to 2 x 11 MiB with a 1024 x 1024 heightfield); further ones
#: are left out with a warning (many records of distinct names could each be kept)
MAX_KEPT_BYTES = 64 * 1024 * 1024


class BagError(Exception):
    """A bag that cannot be read (missing, not MCAP, truncated, corrupt)."""


def warn(message: str) -> None:
    print(f"warning: {message}", file=sys.stderr)


def _norm_type(name: str) -> str:
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[-1]}" if len(parts) == 2 else name


def bag_files(path: str):
    """The .mcap files of a bag: the file itself, or those of a rosbag2 bag directory."""
    if os.path.isdir(path):
        files = glob.glob(os.path.join(path, "*.mcap"))
        if not files:
            other = glob.glob(os.path.join(path, "*.db3"))
            raise BagError(f"{path}: a directory without .mcap files"
                                + (" (sqlite3 bag: convert it with `ros2 bag convert` to mcap)"
                                   if other else ""))

        def natural(p):
            return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p)]
        return sorted(files, key=natural)
    if not os.path.exists(path):
        raise BagError(f"{path}: no such file")
    return [path]


class BagMessages:
    """What :func:`read_messages` read from one bag (an .mcap file or a rosbag2 directory)."""

    def __init__(self, path: str):
        self.path = path
        self.files = []
        self.messages = {}      # selected topic -> [(log_time ns, message)]: decoded, or
                                # its CDR bytes when read with decode=False
        self.decoders = {}      # selected topic -> function(CDR bytes) -> message
        self.types = {}         # every topic of the bag -> 'pkg/msg/Type' ('' without schema)
        self.counts = {}        # every topic of the bag -> number of messages
        self.attachments = {}   # attachment name -> bytes (the first of each name)
        self.metadata = {}      # metadata record name -> dict (the first of each name)
        self.truncated = False  # salvage: reading stopped at damage
        self.total = 0          # messages of every topic
        self.decode_errors = {}  # topic -> [count, first error]
        self.kept_bytes = 0     # of the metadata and attachments kept (MAX_KEPT_BYTES)
        self.left_out = []      # the names of metadata and attachments left out


def check_mcap_file(path: str, salvage: bool = False) -> tuple:
    """(size in bytes, complete) of an MCAP file, after checking that it starts with the MCAP
    magic bytes. Raises BagError for a file that cannot be read or is not MCAP, and for
    a truncated one (no footer magic) unless salvage."""
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
            f.seek(max(0, size - len(MCAP_MAGIC)))
            tail = f.read(len(MCAP_MAGIC))
    except OSError as e:
        raise BagError(f"{path}: cannot read: {e.strerror or e}") from None
    if head != MCAP_MAGIC:
        hint = ""
        if path.endswith(".db3"):
            hint = " (a sqlite3 rosbag2 file: convert it with `ros2 bag convert` to mcap)"
        elif size == 0:
            hint = " (the file is empty)"
        raise BagError(f"{path}: not an MCAP file: it does not start with the MCAP "
                            f"magic bytes{hint}")
    complete = tail == MCAP_MAGIC and size >= 2 * len(MCAP_MAGIC)
    if not complete and not salvage:
        raise BagError(
            f"{path}: truncated MCAP file: it ends without the MCAP footer ({size} bytes). The "
            "recording was not closed (recorder killed, disk full) or the copy is incomplete; "
            "--salvage reads the messages before the damage")
    return size, complete


def mcap_records(f, path: str, size: int, complete: bool, salvage: bool, state: dict,
                 on_warning=None):
    """The records of the open MCAP file f (CRCs checked). At damage: raises BagError,
    or with salvage warns (on_warning, default warn), sets state['truncated'] and stops.
    state['messages'] counts the Message records read."""
    records = iter(StreamReader(f, validate_crcs=True, emit_chunks=True,
                                record_size_limit=min(size + 64, MAX_RECORD_BYTES)).records)
    state.setdefault("messages", 0)
    inner = None                  # the records of the chunk being read
    while True:
        try:
            if inner is not None:
                rec = next(inner, None)
                if rec is None:
                    inner = None
                    continue
            else:
                rec = next(records)
                if isinstance(rec, Chunk):
                    inner = chunk_records(rec)
                    continue
        except StopIteration:
            return
        except Exception as e:   # anything the reader raises: a damaged file
            pos, n = f.tell(), state["messages"]
            reason = f"{type(e).__name__}: {e}".rstrip(": ")
            if not salvage:
                raise BagError(
                    f"{path}: corrupt MCAP file ({reason}, after {n} messages, near byte {pos} "
                    f"of {size}); --salvage reads the messages before the damage") from None
            (on_warning or warn)(
                f"{path}: {'truncated' if not complete else 'damaged'} file: reading stopped "
                f"near byte {pos} of {size} ({reason}); using the {n} messages before it")
            state["truncated"] = True
            return
        if isinstance(rec, Message):
            state["messages"] += 1
        yield rec


def decompress_chunk(chunk) -> bytes:
    """The records section of an MCAP Chunk record, decompressed in bounded pieces (what is
    held is what the data decompresses to, never more than the header's uncompressed_size
    plus one piece; mcap's own reader allocates the size the header or the compressed
    frame claims, 745 GiB for a forged one) and CRC-checked. Raises ValueError."""
    size, comp, data = chunk.uncompressed_size, chunk.compression, chunk.data
    if size > MAX_RECORD_BYTES:
        raise ValueError(f"{comp + '-compressed' if comp else 'uncompressed'} chunk declares "
                         f"{size} bytes of records, more than this reader takes "
                         f"({MAX_RECORD_BYTES >> 20} MiB)")
    if comp == "":
        out = bytes(data)
    elif comp in ("zstd", "lz4"):
        pieces, total = [], 0
        try:
            if comp == "zstd":
                reader = zstandard.ZstdDecompressor().stream_reader(data)
                while total <= size:
                    piece = reader.read(DECOMPRESS_PIECE)
                    if not piece:
                        break
                    pieces.append(piece)
                    total += len(piece)
            else:
                dec = lz4.frame.LZ4FrameDecompressor()
                piece = dec.decompress(data, max_length=DECOMPRESS_PIECE)
                while True:
                    pieces.append(piece)
                    total += len(piece)
                    if dec.eof or total > size or not piece:
                        break
                    piece = dec.decompress(b"", max_length=DECOMPRESS_PIECE)
        except Exception as e:   # the decompressors' own error types
            raise ValueError(f"{comp}-compressed chunk cannot be decompressed: "
                             f"{type(e).__name__}: {e}") from None
        if total != size:
            raise ValueError(f"{comp}-compressed chunk of {len(data)} bytes decompresses to "
                             f"{'more than ' if total > size else ''}{total} bytes, its header "
                             f"says {size}")
        out = b"".join(pieces)
    else:
        raise ValueError(f"chunk with unsupported compression {comp!r}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(out) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch (its records are damaged)")
    return out


def chunk_records(chunk):
    """The Schema, Channel and Message records of a Chunk, one at a time (records of other
    kinds skipped). Raises ValueError at damage (a record running past the chunk's end)."""
    data = decompress_chunk(chunk)
    end = len(data)
    stream = ReadDataStream(io.BytesIO(data))
    while stream.count < end:
        if end - stream.count < 9:
            raise ValueError(f"chunk ends inside a record header ({end - stream.count} bytes)")
        opcode, length = stream.read1(), stream.read8()
        start = stream.count
        if length > end - start:
            raise ValueError(f"a record of {length} bytes runs past the chunk's end "
                             f"({end - start} bytes left)")
        if opcode == Opcode.MESSAGE:
            if length < 22:
                raise ValueError(f"a Message record of {length} bytes (at least 22)")
            rec = Message.read(stream, length)
        elif opcode == Opcode.CHANNEL:
            rec = Channel.read(stream)
        elif opcode == Opcode.SCHEMA:
            rec = Schema.read(stream)
        else:
            rec = None
        used = stream.count - start
        if used > length:
            raise ValueError(f"a record (opcode {opcode:#x}) longer than its length {length}")
        if used < length:
            stream.read(length - used)
        if rec is not None:
            yield rec


def _decoder(factory, rec, schema, path, on_warning):
    """The CDR decoder of channel rec, or None (with a warning) where there is none."""
    try:
        decode = factory.decoder_for(rec.message_encoding, schema)
    except Exception as e:
        on_warning(f"{path}: cannot decode {rec.topic}: {e}")
        return None
    if decode is None:
        on_warning(f"{path}: cannot decode {rec.topic} (message encoding "
                   f"{rec.message_encoding!r}, schema encoding "
                   f"{getattr(schema, 'encoding', None)!r}); ignored")
    return decode


def _stream_file(path: str, bag: BagMessages, on_channel, salvage: bool, on_warning):
    """One MCAP file into bag; see stream_bag."""
    size, complete = check_mcap_file(path, salvage)
    factory = DecoderFactory()
    schemas, handlers, state = {}, {}, {}
    errors = bag.decode_errors
    with open(path, "rb") as f:
        for rec in mcap_records(f, path, size, complete, salvage, state, on_warning):
            if isinstance(rec, Message):
                bag.total += 1
                topic, handle = handlers.get(rec.channel_id, (None, None))
                if topic is None:
                    continue
                bag.counts[topic] += 1
                if handle is None:
                    continue
                if rec.log_time > MAX_TIME_NS or rec.publish_time > MAX_TIME_NS:
                    errors.setdefault(topic, [0, "log or publish time beyond the int64 range "
                                                 f"({max(rec.log_time, rec.publish_time)} ns)"]
                                      )[0] += 1
                    continue
                try:
                    handle(rec)
                except Exception as e:   # a message the schema does not describe
                    errors.setdefault(topic, [0, str(e)])[0] += 1
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel) and rec.id not in handlers:
                schema = schemas.get(rec.schema_id)
                type_name = _norm_type(schema.name) if schema is not None else ""
                bag.types[rec.topic] = type_name
                bag.counts.setdefault(rec.topic, 0)
                handle = on_channel(rec.topic, type_name, functools.partial(
                    _decoder, factory, rec, schema, path, on_warning))
                handlers[rec.id] = (rec.topic, handle)
            elif isinstance(rec, Metadata) and rec.name not in bag.metadata:
                if _keep(bag, rec.name, sum(len(k) + len(v) for k, v in rec.metadata.items())):
                    bag.metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, Attachment) and rec.name not in bag.attachments:
                if _keep(bag, rec.name, len(rec.data)):
                    bag.attachments[rec.name] = bytes(rec.data)
    bag.truncated |= bool(state.get("truncated"))


def _keep(bag, name, size) -> bool:
    """Whether a metadata record or attachment of `size` bytes fits in what is kept
    (MAX_KEPT_BYTES); else its name is noted in bag.left_out."""
    if bag.kept_bytes + size > MAX_KEPT_BYTES:
        bag.left_out.append(name)
        return False
    bag.kept_bytes += size
    return True


def stream_bag(path: str, on_channel, salvage: bool = False, on_warning=None) -> BagMessages:
    """Stream a bag once. For each channel, on_channel(topic, 'pkg/msg/Type', make_decoder)
    returns a handler called with every Message record of that channel (``.data`` CDR bytes,
    ``.log_time``, ``.publish_time``), or None to skip it; make_decoder() gives the
    channel's CDR decoder (or None, with a warning). The returned BagMessages has the
    counts, types, attachments, metadata and decode errors of every topic; `messages` stays
    as the handlers leave it. Warnings go to on_warning(message) (default: stderr)."""
    on_warning = on_warning or warn
    bag = BagMessages(path)
    bag.files = bag_files(path)
    for fpath in bag.files:
        _stream_file(fpath, bag, on_channel, salvage, on_warning)
    if bag.left_out:
        names = ", ".join(repr(n[:60]) for n in bag.left_out[:5])
        on_warning(f"{path}: {len(bag.left_out)} metadata record(s) or attachment(s) left out "
                   f"({names}{', ...' if len(bag.left_out) > 5 else ''}): more than "
                   f"{MAX_KEPT_BYTES} bytes of them in all")
    return bag


def read_messages(path: str, select, salvage: bool = False, decode: bool = True,
                  on_warning=None) -> BagMessages:
    """The messages of every topic for which select(topic, 'pkg/msg/Type') is true, as
    bag.messages[topic] = [(log_time ns, message)]. With decode=False the messages are kept
    as CDR bytes, to be decoded (bag.decoders[topic]) only where needed. A file that is not
    MCAP, truncated or corrupt raises BagError (salvage: read up to the damage, with a
    warning). Messages that cannot be decoded (or whose log time is beyond the int64 range)
    are counted and warned about."""
    on_warning = on_warning or warn
    messages, decoders = {}, {}

    def on_channel(topic, type_name, make_decoder):
        if not select(topic, type_name):
            return None
        dec = make_decoder()
        if dec is None:
            return None
        rows = messages.setdefault(topic, [])
        decoders.setdefault(topic, dec)
        if decode:
            return lambda rec: rows.append((rec.log_time, dec(rec.data)))
        return lambda rec: rows.append((rec.log_time, rec.data))

    bag = stream_bag(path, on_channel, salvage, on_warning)
    bag.messages, bag.decoders = messages, decoders
    for topic, (n, err) in bag.decode_errors.items():
        on_warning(f"{path}: {n} message(s) on {topic} could not be read ({err})")
    return bag


def recorded_robot(bag: BagMessages, path: str):
    """(name, URDF text, spec YAML text or None) of the robot sim_node recorded (its
    'starleth_sim' metadata names the attachments), or None for a bag without them (bags of
    other recorders, and those recorded before the robot was recorded: StarlETH)."""
    meta = bag.metadata.get("starleth_sim", {})
    name = meta.get("robot")
    urdf = bag.attachments.get(meta.get("urdf_attachment", ""))
    if not name or urdf is None:
        return None
    spec = bag.attachments.get(meta.get("robot_spec_attachment") or "")
    try:
        return name, urdf.decode("utf-8"), spec.decode("utf-8") if spec is not None else None
    except UnicodeDecodeError:
        raise BagError(f"{path}: the recorded robot '{name}' is not UTF-8 text") from None
