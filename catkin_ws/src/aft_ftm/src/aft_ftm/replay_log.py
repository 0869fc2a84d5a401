"""SEC's replay floors on stable storage (issue 16: replay protection that survives restarts).

A server gate refuses a request whose id is below its origin's watermark (every id its Proxy said
was answered) and, after a restart, one at or below the highest id an earlier run of the gate let
through (security.ReplayGuard). Both live in memory; this log keeps them across a restart of the
gate, of its site, or of the whole deployment. Before the gate lets a verified request through, the
request's watermark and id are on disk (written, and flushed to the device when ``sync``): a request
the gate forwarded is never unknown to its next run.

The file is an append-only log, one line per change: ``<crc32 hex> <JSON [origin, watermark,
highest]>``. Loading takes each origin's maxima, so the order of lines does not matter (concurrent
writers). A crash may leave the last lines torn (a power loss with unsynced data): those were never
acknowledged, so nothing was forwarded on them, and bad lines at the end are dropped (counted). A bad
line followed by good ones is corruption: loading raises CorruptReplayLog naming the file and the
line, and the gate does not start (it would accept the replays that line recorded). Past
``compact_after`` lines (and twice the origins) the log is rewritten as one line per origin (a
temporary file renamed over it). One gate holds a log at a time (an exclusive lock): a second
one configured with the same path does not start.

Limits: a last line that was synced and then corrupted on the device reads as a torn end, and is
dropped; unsynced lines reaching the device out of order (a power loss) can read as corruption,
which stops the gate though nothing acknowledged was lost (the operator decides).

Writers group their syncs: a writer whose line another's sync covered returns without its own.
"""
import fcntl
import json
import os
import threading
import time
import zlib

from .errors import AftError

COMPACT_AFTER = 20000


class CorruptReplayLog(AftError):
    """The replay log cannot be read back whole; the message names the file and the line."""


def _line(origin, watermark, highest):
    body = json.dumps([origin, watermark, highest], separators=(',', ':'))
    return '%08x %s\n' % (zlib.crc32(body.encode('utf-8')), body)


def _parse(text):
    """(origin, watermark, highest) of one line, or None when it is not a whole, well-formed record."""
    if not text.endswith('\n'):
        return None
    crc, _, body = text[:-1].partition(' ')
    try:
        if len(crc) != 8 or int(crc, 16) != zlib.crc32(body.encode('utf-8')):
            return None
        origin, watermark, highest = json.loads(body)
    except (ValueError, TypeError):
        return None
    if not isinstance(origin, str) or not all(isinstance(v, int) and 0 <= v < 1 << 64
                                              for v in (watermark, highest)):
        return None
    return origin, watermark, highest


def read(path):
    """(floors, dropped): per origin (watermark, highest), the maxima over the log's records, and the
    number of torn lines dropped at its end. A missing file is an empty log. Raises CorruptReplayLog."""
    floors = {}
    bad = []
    try:
        with open(path, 'rb') as f:
            raw = f.read()
    except FileNotFoundError:
        return floors, 0
    except OSError as e:
        raise CorruptReplayLog('replay log %s cannot be read: %s' % (path, e))
    for number, text in enumerate(raw.decode('utf-8', 'replace').splitlines(True), 1):
        record = _parse(text)
        if record is None:
            bad.append(number)
            continue
        if bad:
            raise CorruptReplayLog('replay log %s is corrupt at line %d (a good record follows it at line %d): the '
                                   'replays it recorded would pass; the gate does not start. Remove the file only '
                                   'knowing that every request sent before is then taken again'
                                   % (path, bad[0], number))
        origin, watermark, highest = record
        old = floors.get(origin, (0, 0))
        floors[origin] = (max(old[0], watermark), max(old[1], highest))
    return floors, len(bad)


class ReplayLog(object):
    """The floors of one gate, on disk. ``open()`` reads the log (dropping a torn end) and returns
    what it holds; ``record()`` makes an origin's floors durable before the caller goes on."""

    def __init__(self, path, sync=True, compact_after=COMPACT_AFTER):
        self.path = path
        self.sync = sync
        self.compact_after = compact_after
        self._lock = threading.Lock()        # the file's end and the maxima
        self._sync_lock = threading.Lock()   # one sync (or compaction) at a time; taken before _lock
        self._fd = None
        self._floors = {}    # origin -> [watermark, highest, number of the line that set them]
        self._written = 0    # lines appended so far (numbered from 1)
        self._synced = 0     # lines known durable
        self._lines = 0      # lines in the file now
        self.dropped = 0     # torn lines dropped at open
        self.writes = 0
        self.broken = None   # why the log takes no more lines (a failed write): every record() raises
        self.existed = None  # whether the file was there at open()
        self._lock_file = None

    def open(self, wait=0.0):
        """Read the log and open it for appending; returns {origin: (watermark, highest)}. Raises
        CorruptReplayLog, or OSError when its folder cannot be made, the file opened, or another
        process still holds it after ``wait`` seconds (the gate of a site started again may be ending)."""
        folder = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(folder, mode=0o700, exist_ok=True)
        self._lock_file = open(self.path + '.lock', 'a')
        deadline = time.monotonic() + wait
        while True:
            try:
                fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if time.monotonic() >= deadline:
                    self._lock_file.close()
                    self._lock_file = None
                    raise OSError('replay log %s is held by another process (two gates configured with one log?)'
                                  % self.path)
                time.sleep(0.05)
        self.existed = os.path.exists(self.path)
        floors, self.dropped = read(self.path)
        self._floors = {o: [w, h, 0] for o, (w, h) in floors.items()}
        # A torn end is cut off (rewritten whole): a line appended after it would read as corrupt. A new
        # log is made durable with its folder's entry (a power loss must not lose the file itself).
        if self.dropped or not self.existed:
            self._rewrite()
        else:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND, 0o600)
            with open(self.path, 'rb') as f:
                self._lines = sum(1 for _ in f)
        return floors

    def record(self, origin, watermark, highest):
        """Durable before it returns: the origin's floors at least (watermark, highest). Writes only
        when they rise; otherwise waits for the line that raised them to be durable. Raises OSError
        (nothing was made durable: the caller must not act on the request)."""
        with self._lock:
            if self.broken:
                raise OSError(self.broken)
            old = self._floors.get(origin)
            if old is not None and watermark <= old[0] and highest <= old[1]:
                needed = old[2]
            else:
                watermark = max(watermark, old[0]) if old else watermark
                highest = max(highest, old[1]) if old else highest
                data = _line(origin, watermark, highest).encode('utf-8')
                try:
                    written = os.write(self._fd, data)
                    if written != len(data):
                        raise OSError('%d of %d bytes written' % (written, len(data)))
                except OSError as e:
                    # A part of a line may be on disk: a line after it would make the log corrupt. It
                    # takes no more (the next run drops the torn end).
                    self.broken = 'replay log %s failed a write (%s): it takes no more records' % (self.path, e)
                    raise OSError(self.broken)
                self._written += 1
                self._lines += 1
                self.writes += 1
                needed = self._written
                self._floors[origin] = [watermark, highest, needed]
        self._make_durable(needed)
        if self._lines > self._bound():
            with self._sync_lock, self._lock:
                if self._lines > self._bound() and not self.broken:
                    try:
                        self._rewrite()
                    except OSError as e:
                        self.broken = 'replay log %s failed its compaction (%s): it takes no more records' % (
                            self.path, e)
                        raise OSError(self.broken)

    def _bound(self):
        """Lines past which the log is compacted: never less than twice its origins (a compaction at
        every write past compact_after origins would stall every writer)."""
        return max(self.compact_after, 2 * len(self._floors))

    def _make_durable(self, needed):
        if needed == 0 or not self.sync:
            return
        with self._sync_lock:
            if self._synced >= needed:
                return   # another writer's sync covered this line
            with self._lock:
                if self.broken:   # a failed sync: its pages may be lost, and a second sync says nothing
                    raise OSError(self.broken)
                upto = self._written
                fd = self._fd
            try:
                os.fdatasync(fd)
            except OSError as e:
                with self._lock:
                    self.broken = 'replay log %s failed a sync (%s): it takes no more records' % (self.path, e)
                raise OSError(self.broken)
            self._synced = max(self._synced, upto)

    def _rewrite(self):
        """The log as one line per origin, durable, renamed over the old one. Every line is durable then."""
        folder = os.path.dirname(os.path.abspath(self.path))
        tmp = '%s.%d.tmp' % (self.path, os.getpid())
        data = ''.join(_line(o, w, h) for o, (w, h, _) in sorted(self._floors.items())).encode('utf-8')
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            view = memoryview(data)
            while view:
                written = os.write(fd, view)
                if written <= 0:
                    raise OSError('%s: nothing written' % tmp)
                view = view[written:]
            os.fsync(fd)
        except OSError:
            os.close(fd)
            os.unlink(tmp)
            raise
        os.close(fd)
        os.rename(tmp, self.path)
        dir_fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
        if self._fd is not None:
            os.close(self._fd)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND, 0o600)
        self._lines = len(self._floors)
        self._synced = self._written
        for entry in self._floors.values():
            entry[2] = 0

    def origins(self):
        with self._lock:
            return len(self._floors)

    def close(self):
        with self._sync_lock, self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None
            if getattr(self, '_lock_file', None) is not None:
                self._lock_file.close()   # (closing it releases the lock)
                self._lock_file = None
