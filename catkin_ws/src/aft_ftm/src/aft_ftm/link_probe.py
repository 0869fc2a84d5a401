"""Measuring the bandwidth between two sites, for the monitor's R (no rospy here).

The monitor adapts when the available bandwidth no longer supports the running mechanism (PBR's
checkpoints need a high one, Table I). Nothing on an idle link tells its capacity, so the link
monitor measures it: a *probe* streams filler bytes over TCP to the peer's *sink* for a short
while (``seconds``, at most ``max_bytes``), and the sink, which sees the bytes arrive at the
rate the link lets through, answers with what it received and over how long. The rate is
measured at the receiving end: the sender's figure would count what its own socket buffer took.
A token bucket's burst (what passes at once before the limit bites) arrives with the first
bytes, so the first ``skip`` bytes only start the clock.

A probe costs the link at most ``seconds`` of its capacity plus the sender's socket buffer (kept
small: ``SEND_BUFFER``). :class:`Estimator` reports the median of the last few probes, so that one
probe slowed by a burst of checkpoints does not switch the mechanism.

Wire format, in both directions: one header line of ASCII, then (probe only) the bytes.
  probe -> sink:  ``AFTPROBE 1\\n`` then bytes, then the write side is shut down (EOF);
  sink -> probe:  ``AFTSINK 1 <bytes> <seconds>\\n``.
Anything else is refused with a message naming what was wrong; a sink never waits for ever
(``timeout`` on every read, ``max_seconds`` and ``max_bytes`` for a whole probe).
"""
import socket
import statistics
import threading
import time

from .errors import AftError, ConfigError

PROBE_HEADER = b'AFTPROBE 1\n'
SINK_PREFIX = 'AFTSINK 1'
CHUNK = 16384
SEND_BUFFER = 16384
MAX_LINE = 128
SINK_MAX_BYTES = 256 << 20    # a sink takes at most this from one probe (64 times the default probe's)
SINK_MAX_SECONDS = 60.0       # ... and for at most this long (a probe streams for a fraction of a second)


class ProbeError(AftError):
    """A probe could not measure the link (peer unreachable, no answer, a malformed answer)."""


def check_endpoint(name, value):
    """``host:port`` -> (host, port); a bad value raises ConfigError naming the parameter."""
    if not isinstance(value, str) or value.count(':') != 1:
        raise ConfigError('parameter %s: expected host:port, got %r' % (name, value))
    host, port = value.split(':')
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError('parameter %s: expected host:port with a port in 1..65535, got %r' % (name, value))
    return host, int(port)


def parse_answer(line):
    """The sink's answer line -> (bytes, seconds). Raises ProbeError naming a malformed answer."""
    parts = line.split()
    if len(parts) != 4 or ' '.join(parts[:2]) != SINK_PREFIX:
        raise ProbeError('malformed answer from the sink: %r' % line[:MAX_LINE])
    try:
        count, seconds = int(parts[2]), float(parts[3])
    except ValueError:
        raise ProbeError('malformed answer from the sink: %r' % line[:MAX_LINE])
    if count < 0 or not seconds >= 0:
        raise ProbeError('impossible answer from the sink: %r' % line[:MAX_LINE])
    return count, seconds


def rate(count, seconds):
    """Bytes per second of a measurement, or None when it is too short to tell (all in one burst)."""
    if count <= 0 or seconds <= 0:
        return None
    return count / seconds


class Measure(object):
    """What a sink saw of one probe: bytes after the first ``skip``, and the time they took."""

    def __init__(self, skip):
        self.skip = skip
        self.total = 0
        self.start = None
        self.last = None
        self.counted = 0

    def add(self, n, now):
        self.total += n
        if self.start is None:
            if self.total >= self.skip:
                self.start = now   # the burst is through: the clock starts
            return
        self.counted += n
        self.last = now

    def result(self):
        if self.start is None or self.last is None:
            return 0, 0.0
        return self.counted, self.last - self.start


class Estimator(object):
    """The bandwidth reported: the median of the last ``window`` probes (bytes/s)."""

    def __init__(self, window=3):
        if window < 1:
            raise ConfigError('window: expected at least 1 probe, got %r' % (window,))
        self.window = window
        self.samples = []
        self.failures = 0          # probes in a row that measured nothing

    def add(self, bytes_per_s):
        if bytes_per_s is None:
            self.failures += 1
            return
        self.failures = 0
        self.samples = (self.samples + [bytes_per_s])[-self.window:]

    def estimate(self):
        return statistics.median(self.samples) if self.samples else None


def probe(endpoint, seconds=0.2, max_bytes=4 << 20, timeout=5.0, source=None):
    """Stream filler to the sink at ``endpoint`` (host, port) for ``seconds`` or ``max_bytes``;
    the sink's (bytes, seconds). Raises ProbeError naming what failed; never waits past ``timeout``
    plus the time the sink takes to drain the send buffer at the measured rate."""
    deadline = time.monotonic() + timeout
    filler = b'\0' * CHUNK
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    except OSError as e:
        raise ProbeError('cannot make a socket: %s' % e)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        if source:
            sock.bind((source, 0))
        sock.settimeout(timeout)
        try:
            sock.connect(endpoint)
            sock.sendall(PROBE_HEADER)
            sent, stop = 0, time.monotonic() + seconds
            while sent < max_bytes and time.monotonic() < stop:
                sock.settimeout(max(0.01, min(stop, deadline) - time.monotonic()))
                try:
                    sent += sock.send(filler[:min(CHUNK, max_bytes - sent)])
                except socket.timeout:
                    break         # the link takes less than we offer in the time: that is the measure
            sock.shutdown(socket.SHUT_WR)
            sock.settimeout(max(0.1, deadline - time.monotonic()) + seconds)
            line = _read_line(sock)
        except (OSError, socket.timeout) as e:
            raise ProbeError('probe of %s:%d failed: %s' % (endpoint[0], endpoint[1], e or type(e).__name__))
        return parse_answer(line)
    finally:
        sock.close()


def _read_line(sock):
    data = b''
    while b'\n' not in data:
        chunk = sock.recv(MAX_LINE)
        if not chunk:
            break
        data += chunk
        if len(data) > MAX_LINE:
            break
    return data.split(b'\n', 1)[0].decode('ascii', 'replace')


class Sink(object):
    """Answers probes on (host, port) (port 0: any free one, see ``endpoint``), one at a time, in a
    daemon thread. ``skip``: the bytes of the burst a token bucket lets through at once. A probe still
    sending after ``max_seconds`` or past ``max_bytes`` is refused (review of session 34: a peer trickling
    bytes held the sink for ever)."""

    def __init__(self, host, port=0, skip=8192, timeout=5.0, clock=time.monotonic, max_seconds=SINK_MAX_SECONDS,
                 max_bytes=SINK_MAX_BYTES):
        self.skip = skip
        self.timeout = timeout
        self.max_seconds = max_seconds
        self.max_bytes = max_bytes
        self.clock = clock
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind((host, port))
        self.server.listen(4)
        self.endpoint = self.server.getsockname()[:2]
        self.served = 0
        self.refused = []          # why each refused probe was refused (last 10)
        self._closed = threading.Event()
        self.thread = threading.Thread(target=self._serve, name='link-sink', daemon=True)

    def start(self):
        self.thread.start()
        return self

    def close(self):
        self._closed.set()
        try:
            self.server.close()
        except OSError:
            pass

    def _serve(self):
        while not self._closed.is_set():
            try:
                conn, _ = self.server.accept()
            except OSError:
                return   # closed
            try:
                self._answer(conn)
            except (OSError, socket.timeout, ProbeError) as e:
                self.refused = (self.refused + [str(e) or type(e).__name__])[-10:]
            finally:
                conn.close()

    def _answer(self, conn):
        deadline = time.monotonic() + self.max_seconds
        conn.settimeout(self.timeout)
        header = b''
        while len(header) < len(PROBE_HEADER):
            chunk = conn.recv(len(PROBE_HEADER) - len(header))
            if not chunk:
                break
            header += chunk
        if header != PROBE_HEADER:
            raise ProbeError('not a probe: header %r' % header[:MAX_LINE])
        measure = Measure(self.skip)
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ProbeError('probe still sending after %g s: refused' % self.max_seconds)
            conn.settimeout(min(self.timeout, left))
            try:
                chunk = conn.recv(65536)
            except socket.timeout:
                if time.monotonic() < deadline:
                    raise
                raise ProbeError('probe still sending after %g s: refused' % self.max_seconds)
            if not chunk:
                break
            measure.add(len(chunk), self.clock())
            if measure.total > self.max_bytes:
                raise ProbeError('probe of more than %d bytes: refused' % self.max_bytes)
        count, seconds = measure.result()
        self.served += 1   # before the answer: the prober may look as soon as it has it (a unit test did)
        conn.sendall(('%s %d %.6f\n' % (SINK_PREFIX, count, seconds)).encode('ascii'))
