"""Does ROS 1 lose messages while a subscriber is stopped with SIGSTOP? (scripts/bench_ros_buffering)

The paper (section 6.1) says "a publisher node buffers all on-going messages until all its subscriber
nodes read them. Thus stopping a node (SIGSTOP) is safe". This module measures it with rospy:

* the parent (this process, a rospy node) owns a Publisher; each configuration gets a fresh topic and
  a fresh subscriber in a child process (:func:`subscriber_main`) that records every sequence number;
* phases: warm-up messages (flagged, not counted) until the child has heard one, then ``pre`` seconds
  of publishing at a fixed rate, SIGSTOP of the child for ``stop`` seconds while publishing goes on,
  SIGCONT, ``post`` seconds more; then the child drains (until its last message came or it heard
  nothing for ``quiet`` seconds, bounded) and writes what it received as JSON;
* where a lost message went is read from rospy's own counter: the publisher connection counts the
  messages it wrote to the socket; the rest were dropped by the publisher's queue (rospy's
  ``QueuedConnection`` drops the oldest once ``queue_size`` is reached). TCP delivers everything
  written once the child has drained, so what was written but never delivered to the callback was
  dropped by the subscriber's queue (rospy keeps only the last ``queue_size`` messages of each socket
  read, up to 64 KB). What the publisher wrote while the child was stopped went into the kernel's TCP
  buffers: that is "absorbed by TCP". (The subscriber's byte counter is kept in the JSON as a
  cross-check; it misses what the handshake read happened to pull in with the header.)

The child talks to the parent through its stdin/stdout: it prints ``FIRST`` once it heard a message
and reads ``DRAIN <last seq>`` (or end of file, if the parent died) before draining.
"""
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time

from aft_bench import machine
from aft_examples.stats import median

SEQ_DIGITS = 12
WARMUP_MARK = 'W'


class BenchError(Exception):
    """A configuration could not be measured (a process did not come up, answer or stop)."""


# -- pure part: messages, analysis, report (no rospy) ------------------------------------------------

def payload_text(seq, size, warmup=False):
    """The String data of message ``seq``: its number, zero-padded, then padding up to ``size`` bytes.
    Warm-up messages have the same size (so that bytes read count messages) and a mark instead."""
    head = (WARMUP_MARK + '%0*d' % (SEQ_DIGITS - 1, seq)) if warmup else '%0*d' % (SEQ_DIGITS, seq)
    return head + 'x' * max(0, size - SEQ_DIGITS)


def parse_payload(data):
    """(seq, is_warmup) from a message's data."""
    if data[0] == WARMUP_MARK:
        return int(data[1:SEQ_DIGITS]), True
    return int(data[:SEQ_DIGITS]), False


def analyse(sent_wall, received, stop_window, accounting):
    """Figures of one run.

    sent_wall: publish wall time of each measured message, indexed by sequence number;
    received: sequence numbers in the order the subscriber got them (measured messages only);
    stop_window: (wall time of SIGSTOP, wall time of SIGCONT);
    accounting: dict with 'published_total', 'written_total' (publisher side) and 'delivered_total'
    (subscriber side), all including warm-up messages, and 'written_during_stop'.
    """
    sent = len(sent_wall)
    distinct = set(received)
    lost = [s for s in range(sent) if s not in distinct]
    t_stop, t_cont = stop_window
    before = sum(1 for s in lost if sent_wall[s] < t_stop)
    during = sum(1 for s in lost if t_stop <= sent_wall[s] < t_cont)
    pub_dropped = accounting['published_total'] - accounting['written_total']
    sub_dropped = accounting['written_total'] - accounting['delivered_total']
    return {
        'sent': sent, 'received': len(distinct), 'lost': len(lost),
        'lost_pct': 100.0 * len(lost) / sent if sent else 0.0,
        'duplicated': len(received) - len(distinct),
        'out_of_order': sum(1 for a, b in zip(received, received[1:]) if b < a),
        'sent_during_stop': sum(1 for t in sent_wall if t_stop <= t < t_cont),
        'lost_before_stop': before, 'lost_during_stop': during, 'lost_after_stop': len(lost) - before - during,
        'dropped_by_publisher_queue': pub_dropped, 'dropped_by_subscriber_queue': sub_dropped,
        'absorbed_by_tcp_during_stop': accounting['written_during_stop'],
        'first_lost': lost[0] if lost else None, 'last_lost': lost[-1] if lost else None,
    }


FIGURES = ('sent', 'received', 'lost', 'lost_pct', 'duplicated', 'sent_during_stop', 'lost_during_stop',
           'dropped_by_publisher_queue', 'dropped_by_subscriber_queue',
           'absorbed_by_tcp_during_stop')


def summarise(runs):
    """One row from the repetitions of a configuration: the median of each figure."""
    return {k: median([r[k] for r in runs]) for k in FIGURES}


def _fmt(x):
    return ('%d' % x) if float(x).is_integer() else ('%.1f' % x)


def format_table(rows):
    """Markdown table; rows are dicts with payload, payload_bytes, queue_size, stop_s, repeats and FIGURES."""
    head = ('| payload | queue | stop (s) | runs | sent | received | lost | lost % | lost in stop window '
            '| dropped: pub queue | dropped: sub queue | absorbed by TCP during stop |')
    lines = [head, '|' + '---|' * (head.count('|') - 1)]
    for r in rows:
        lines.append('| %s (%d B) | %d | %g | %d | %s | %s | %s | %.1f | %s | %s | %s | %s |' % (
            r['payload'], r['payload_bytes'], r['queue_size'], r['stop_s'], r['repeats'], _fmt(r['sent']),
            _fmt(r['received']), _fmt(r['lost']), r['lost_pct'], _fmt(r['lost_during_stop']),
            _fmt(r['dropped_by_publisher_queue']), _fmt(r['dropped_by_subscriber_queue']),
            _fmt(r['absorbed_by_tcp_during_stop'])))
    return '\n'.join(lines)


def _size(n):
    return '%.1f MB' % (n / 1e6) if n >= 1e6 else '%.1f KB' % (n / 1e3)


def _trend(rows, along, across):
    """'grow'/'shrink'/'flat'/'mixed': how losses move as ``along`` increases, for every value of ``across``."""
    signs = set()
    for key in sorted({r[across] for r in rows}):
        series = [r['lost'] for r in sorted((r for r in rows if r[across] == key), key=lambda r: r[along])]
        for a, b in zip(series, series[1:]):
            signs.add((b > a) - (b < a))
    if signs <= {0}:
        return 'flat'
    if signs <= {0, 1}:
        return 'grow'
    if signs <= {0, -1}:
        return 'shrink'
    return 'mixed'


def _where(pub, subq):
    if pub == 0 and subq == 0:
        return 'nothing dropped'
    if pub == 0:
        return 'all %s dropped by the subscriber queue' % _fmt(subq)
    if subq == 0:
        return 'all %s dropped by the publisher queue' % _fmt(pub)
    return '%s dropped by the publisher queue, %s by the subscriber queue' % (_fmt(pub), _fmt(subq))


_TRENDS = {'grow': 'grow', 'shrink': 'shrink', 'flat': 'do not change', 'mixed': 'are not monotonic'}


def conclusions(rows):
    """One line per payload and one on the paper's claim, computed from the rows."""
    out = []
    for payload in sorted({r['payload'] for r in rows}, key=lambda p: min(r['payload_bytes'] for r in rows
                                                                          if r['payload'] == p)):
        sub = [r for r in rows if r['payload'] == payload]
        size = sub[0]['payload_bytes']
        queues = sorted({r['queue_size'] for r in sub})
        stops = sorted({r['stop_s'] for r in sub})
        lossy = [r for r in sub if r['lost'] > 0]
        absorbed = max(r['absorbed_by_tcp_during_stop'] for r in sub)
        if all(r['absorbed_by_tcp_during_stop'] >= r['sent_during_stop'] for r in sub):
            tcp = 'TCP buffers took every message sent during the stops (up to %s, %s)' % (
                _fmt(absorbed), _size(absorbed * size))
        else:
            tcp = 'TCP buffers took at most %s messages (%s) per stop, the rest queued in the publisher' % (
                _fmt(absorbed), _size(absorbed * size))
        if not lossy:
            out.append('%s messages (%d B): 0 lost up to %g s stops whatever the queue (%s); %s.'
                       % (payload, size, max(stops), '/'.join(map(str, queues)), tcp))
            continue
        where = _where(sum(r['dropped_by_publisher_queue'] for r in sub),
                       sum(r['dropped_by_subscriber_queue'] for r in sub))
        clean = ['q=%d/%gs' % (r['queue_size'], r['stop_s']) for r in sub if r['lost'] == 0]
        trends = []
        if len(stops) > 1:
            trends.append('losses %s with stop time' % _TRENDS[_trend(sub, 'stop_s', 'queue_size')])
        if len(queues) > 1:
            trends.append('%s with queue size' % _TRENDS[_trend(sub, 'queue_size', 'stop_s')])
        out.append('%s messages (%d B): lost in %d of %d configurations (%s); %s; lossless only: %s; %s.'
                   % (payload, size, len(lossy), len(sub), where, ', '.join(trends),
                      ', '.join(clean) if clean else 'none', tcp))
    bad = [r for r in rows if r['lost'] > 0]
    out.append('Claim "stopping a subscriber with SIGSTOP loses no message": %s.'
               % ('holds in all %d configurations' % len(rows) if not bad else
                  'fails in %d of %d configurations' % (len(bad), len(rows))))
    return out


# -- the subscriber child --------------------------------------------------------------------------------

class _Recorder(object):
    def __init__(self):
        self.lock = threading.Lock()
        self.seqs, self.times = [], []
        self.warmups = 0
        self.delivered = 0
        self.max_seq = -1
        self.last_rx = None
        self.first = threading.Event()

    def on_message(self, msg):
        now = time.time()
        seq, warmup = parse_payload(msg.data)
        with self.lock:
            self.delivered += 1
            self.last_rx = time.monotonic()
            if warmup:
                self.warmups += 1
            else:
                self.seqs.append(seq)
                self.times.append(now)
                self.max_seq = max(self.max_seq, seq)
        self.first.set()


def _bytes_read(conn):
    """Bytes a subscriber connection read from its socket: rospy's stat_bytes also counts the
    handshake header the subscriber wrote (and not the one it read)."""
    from rosgraph.network import encode_ros_handshake_header
    return conn.stat_bytes - len(encode_ros_handshake_header(conn.protocol.get_header_fields()))


def subscriber_main(topic, queue_size, out_path, quiet=1.0, max_drain=20.0, first_timeout=30.0):
    """The child: subscribe, report the first message, wait for DRAIN, drain, write JSON to out_path."""
    import rospy
    from std_msgs.msg import String
    rospy.init_node('buffering_sub', anonymous=True)
    rec = _Recorder()
    sub = rospy.Subscriber(topic, String, rec.on_message, queue_size=queue_size)
    if not rec.first.wait(first_timeout):
        sys.stderr.write('no message on %s within %.0f s\n' % (topic, first_timeout))
        return 2
    sys.stdout.write('FIRST\n')
    sys.stdout.flush()
    line = sys.stdin.readline().split()   # blocks until the parent is done publishing (or died)
    last_seq = int(line[1]) if len(line) == 2 and line[0] == 'DRAIN' else None
    started = time.monotonic()
    ended = 'timeout'
    while time.monotonic() - started < max_drain:
        with rec.lock:
            idle = time.monotonic() - rec.last_rx
            complete = last_seq is not None and rec.max_seq >= last_seq
        if complete and idle >= 0.2:      # TCP is in order: nothing sent before the last one can still come
            ended = 'last message received'
            break
        if idle >= quiet:
            ended = 'quiet for %.1f s' % quiet
            break
        time.sleep(0.01)
    with rec.lock:
        result = {'seqs': rec.seqs, 'recv_wall': rec.times, 'warmups': rec.warmups, 'delivered': rec.delivered,
                  'bytes_read': sum(_bytes_read(c) for c in sub.impl.connections),
                  'drain_s': time.monotonic() - started, 'drain_ended': ended}
    with open(out_path + '.tmp', 'w') as f:
        json.dump(result, f)
    os.rename(out_path + '.tmp', out_path)
    rospy.signal_shutdown('drained')
    return 0


class SubscriberProcess(object):
    """The child subscriber seen from the parent: start, wait for FIRST, stop/continue, drain, stop."""

    def __init__(self, argv, log_path):
        self.argv = argv
        self.log_path = log_path
        self.proc = None
        self._buf = b''
        self._log = None

    def start(self):
        self._log = open(self.log_path, 'ab')
        self.proc = subprocess.Popen(self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log,
                                     start_new_session=True)   # our Ctrl-C is for us: we stop it ourselves
        return self

    def alive(self):
        return self.proc is not None and self.proc.poll() is None

    def read_line(self, timeout):
        """The next line the child printed, or None after timeout seconds or if it closed its stdout."""
        deadline = time.monotonic() + timeout
        fd = self.proc.stdout.fileno()
        while b'\n' not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 4096)
                if not chunk:
                    return None
                self._buf += chunk
        line, self._buf = self._buf.split(b'\n', 1)
        return line.decode(errors='replace').strip()

    def signal(self, sig):
        if self.alive():
            os.kill(self.proc.pid, sig)

    def drain(self, last_seq, timeout):
        """Tell the child publishing is over; True if it exited by itself within timeout."""
        self.proc.stdin.write(b'DRAIN %d\n' % last_seq)
        self.proc.stdin.flush()
        try:
            self.proc.wait(timeout)
            return True
        except subprocess.TimeoutExpired:
            return False

    def stop(self, grace=5.0):
        """SIGCONT (a stopped process cannot handle SIGINT), SIGINT, then SIGKILL after grace. Never raises."""
        try:
            if self.proc is not None and self.proc.poll() is None:
                for sig in (signal.SIGCONT, signal.SIGINT):
                    self.signal(sig)
                try:
                    self.proc.wait(grace)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(grace)
        except Exception:   # shutdown paths never raise
            pass
        finally:
            for f in (self.proc and self.proc.stdin, self.proc and self.proc.stdout, self._log):
                try:
                    if f:
                        f.close()
                except Exception:
                    pass


# -- the parent: one configuration -----------------------------------------------------------------------

def run_config(child_argv, work_dir, name, payload_bytes, queue_size, stop_s, rate=100.0, pre=0.5, post=0.5,
               quiet=1.0, max_drain=20.0, timeout=30.0):
    """Measure one configuration in a fresh subscriber child; returns analyse()'s figures plus raw data.

    child_argv: the command that runs :func:`subscriber_main` given ``--topic T --queue-size Q --out F``.
    """
    import rospy
    from std_msgs.msg import String
    from aft_ftm.sites import wait_until
    topic = '/bench_buffering/%s' % name
    out_path = os.path.join(work_dir, name + '.json')
    period = 1.0 / rate
    pub = rospy.Publisher(topic, String, queue_size=queue_size)
    child = SubscriberProcess(child_argv + ['--topic', topic, '--queue-size', str(queue_size), '--out', out_path,
                                            '--quiet', str(quiet), '--max-drain', str(max_drain)],
                              os.path.join(work_dir, name + '.log'))
    try:
        child.start()
        if not wait_until(lambda: pub.get_num_connections() >= 1 or not child.alive(), timeout, 0.005) \
                or not child.alive():
            raise BenchError('%s: the subscriber did not connect (log %s)' % (name, child.log_path))
        conn = pub.impl.connections[0]   # keep it: rospy forgets a connection once closed
        # warm-up: flagged messages until the child has heard one (connection up end to end)
        warmups = 0
        deadline = time.monotonic() + timeout
        line = None
        while line != 'FIRST':
            if time.monotonic() > deadline or not child.alive():
                raise BenchError('%s: the subscriber heard nothing (log %s)' % (name, child.log_path))
            pub.publish(String(payload_text(warmups, payload_bytes, warmup=True)))
            warmups += 1
            line = child.read_line(period)
        # measured phases
        sent_wall = []
        t0 = time.monotonic()
        stop_at, cont_at = t0 + pre, t0 + pre + stop_s
        end_at = cont_at + post
        t_stop = t_cont = None
        written_at_stop = written_at_cont = 0
        while True:
            now = time.monotonic()
            if t_stop is None and now >= stop_at:
                child.signal(signal.SIGSTOP)
                t_stop, written_at_stop = time.time(), conn.stat_num_msg
            if t_stop is not None and t_cont is None and now >= cont_at:
                written_at_cont = conn.stat_num_msg
                child.signal(signal.SIGCONT)
                t_cont = time.time()
            if now >= end_at:
                break
            due = t0 + len(sent_wall) * period
            if now >= due:
                pub.publish(String(payload_text(len(sent_wall), payload_bytes)))
                sent_wall.append(time.time())
                continue
            time.sleep(max(0.0, min(due, stop_at if t_stop is None else cont_at if t_cont is None else end_at)
                           - now))
        publish_s = time.monotonic() - t0
        if not child.drain(len(sent_wall) - 1, max_drain + timeout):
            raise BenchError('%s: the subscriber did not finish draining (log %s)' % (name, child.log_path))
        if not os.path.exists(out_path):
            raise BenchError('%s: the subscriber wrote no result, exit %s (log %s)'
                             % (name, child.proc.returncode, child.log_path))
        with open(out_path) as f:
            got = json.load(f)
        wire = 4 + 4 + payload_bytes   # TCPROS length prefix + String length prefix + data
        accounting = {'published_total': warmups + len(sent_wall), 'written_total': conn.stat_num_msg,
                      'bytes_read': got['bytes_read'], 'wire_bytes': wire, 'delivered_total': got['delivered'],
                      'written_during_stop': written_at_cont - written_at_stop,
                      'warmups_lost': warmups - got['warmups']}
        figures = analyse(sent_wall, got['seqs'], (t_stop, t_cont), accounting)
        delays = [t - sent_wall[s] for s, t in zip(got['seqs'], got['recv_wall']) if s < len(sent_wall)]
        figures.update({'publish_rate_hz': len(sent_wall) / publish_s, 'warmups': warmups,
                        'max_delay_s': max(delays) if delays else None, 'drain_s': got['drain_s'],
                        'drain_ended': got['drain_ended'], 'accounting': accounting})
        return figures
    finally:
        child.stop()
        pub.unregister()


def machine_description():
    """Lines describing the machine and the ROS version, for the top of the report."""
    m = machine.describe()
    return ['ROS: %s; rospy package: %s; Python %s' % (m['ros_comm'], m['rospy'], m['python']),
            'CPUs: %d; %s' % (m['cpus'], m['system']),
            'TCP buffers (min default max): net.ipv4.tcp_rmem %s, tcp_wmem %s' % (m['tcp_rmem'], m['tcp_wmem'])]
