"""Power switches, carried out: asking one (:func:`call_switch`) and serving one (:class:`SwitchServer`).

The request/answer format and what counts as "confirmed off" are in :mod:`aft_ftm.power_switch`.
"""
import os
import socket
import socketserver
import subprocess
import threading

from .power_switch import (SwitchError, Outcome, answer_outcome, command_outcome, encode_answer, encode_request,
                           parse_request, MAX_LINE)


def call_switch(spec, host, timeout):
    """Ask the switch ``spec`` (a SwitchSpec) to power ``host`` off; an Outcome, never raises.

    The answer is awaited at most ``timeout`` seconds: a switch that does not answer in time has not
    confirmed anything.
    """
    if spec.kind == 'unix':
        return _call_unix(spec.path, host, timeout)
    argv = spec.command_for(host)
    try:
        done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              timeout=timeout)
    except FileNotFoundError:
        return Outcome(False, 'fence command %s: no such program: %s may still run' % (argv[0], host))
    except subprocess.TimeoutExpired:
        return Outcome(False, 'fence command %s did not finish within %g s: %s may still run'
                       % (' '.join(argv), timeout, host))
    except OSError as e:
        return Outcome(False, 'fence command %s could not run (%s): %s may still run' % (argv[0], e, host))
    return command_outcome(argv, done.returncode, done.stdout.decode(errors='replace'), host)


def _call_unix(path, host, timeout):
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(timeout)
            s.connect(path)
            s.sendall(encode_request('off', host))
            line = _read_line(s)
    except socket.timeout:
        return Outcome(False, 'the switch %s did not answer within %g s: %s may still run' % (path, timeout, host))
    except OSError as e:
        return Outcome(False, 'the switch %s cannot be reached (%s): %s may still run' % (path, e, host))
    return answer_outcome(line, host)


def _read_line(sock):
    data = b''
    while not data.endswith(b'\n') and len(data) <= MAX_LINE:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    return data


class SwitchServer(object):
    """A power switch agent on a Unix-domain socket (mode 0600), one thread per request.

    ``power_off(host)`` must return only once the host is off (a detail string), and raise naming the
    problem if it cannot; ``state(host)`` returns 'off', or another word. An ``off`` request of a host
    already off is answered ``off`` at once. :meth:`refuse` makes it refuse every request (tests).
    """

    def __init__(self, path, power_off, state, log=None):
        self.path = path
        self._power_off = power_off
        self._state = state
        self.log = log or (lambda message: None)
        self.refusing = None
        self.requests = []        # (op, host, ok) of every request answered, in order
        self._lock = threading.Lock()
        self._server = None
        self._thread = None

    def start(self):
        if os.path.exists(self.path):
            os.unlink(self.path)
        outer = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self):
                self.wfile.write(outer._answer(self.rfile.readline(MAX_LINE + 1)))

        self._server = socketserver.ThreadingUnixStreamServer(self.path, Handler)
        self._server.daemon_threads = True
        os.chmod(self.path, 0o600)
        self._thread = threading.Thread(target=self._server.serve_forever, name='power-switch', daemon=True)
        self._thread.start()
        return self

    def refuse(self, reason):
        """Refuse every request from now on with ``reason`` (None: serve again)."""
        self.refusing = reason

    def _answer(self, line):
        op, host = '?', '?'
        try:
            op, host = parse_request(line)
            if self.refusing:
                raise SwitchError(self.refusing)
            if op == 'status':
                answer = encode_answer(host, True, self._state(host))
            elif self._state(host) == 'off':
                answer = encode_answer(host, True, 'off', 'already off')
            else:
                with self._lock:   # one power-off at a time
                    detail = self._power_off(host)
                answer = encode_answer(host, True, 'off', detail)
            ok = True
        except Exception as e:   # the caller gets the reason; the switch goes on serving
            answer, ok = encode_answer(host, False, error=str(e)), False
        self.requests.append((op, host, ok))
        self.log('power switch: %s' % answer.decode().strip())
        return answer

    def stop(self):
        """Stop serving and remove the socket. Idempotent; never raises."""
        try:
            if self._server is not None:
                self._server.shutdown()
                self._server.server_close()
                self._server = None
            if os.path.exists(self.path):
                os.unlink(self.path)
        except Exception as e:   # shutdown paths never raise
            self.log('power switch: stop: %s' % e)
