"""Plain-socket peers that the emulated-hosts test starts inside hosts (not a test module).

  serve PORT            TCP server: first byte E = echo, S = count bytes until EOF, reply the count
  probe HOST PORT T     one echo round trip with timeout T: prints "ok SECONDS" or "fail ERROR SECONDS"
  send HOST PORT N      N bytes to a sink: prints "sent N SECONDS" (until the count came back)
  hold HOST PORT        opens an echo connection, prints "connected"; then per stdin line "recv T"
                        prints what a recv with timeout T saw: data, closed, reset or timeout
  tick                  prints time.monotonic() every 20 ms
  daemon                forks a grandchild in a session of its own that prints its pid and sleeps
"""
import os
import socket
import sys
import threading
import time


def out(*words):
    sys.stdout.write(' '.join(str(w) for w in words) + '\n')
    sys.stdout.flush()


def serve(port):
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(('0.0.0.0', port))
    server.listen(16)
    out('ready')
    while True:
        conn, _ = server.accept()
        threading.Thread(target=handle, args=(conn,), daemon=True).start()


def handle(conn):
    with conn:
        mode = conn.recv(1)
        if mode == b'E':
            while True:
                data = conn.recv(65536)
                if not data:
                    return
                conn.sendall(data)
        elif mode == b'S':
            count = 0
            while True:
                data = conn.recv(65536)
                if not data:
                    break
                count += len(data)
            conn.sendall(str(count).encode())


def probe(host, port, timeout):
    start = time.monotonic()
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.sendall(b'Eping')
            got = b''
            while len(got) < 4:
                data = s.recv(4 - len(got))
                if not data:
                    raise ConnectionError('closed')
                got += data
        out('ok', '%.6f' % (time.monotonic() - start))
    except (OSError, ConnectionError) as e:
        out('fail', type(e).__name__, '%.4f' % (time.monotonic() - start))


def send(host, port, n):
    block = b'x' * 65536
    with socket.create_connection((host, port), timeout=20) as s:
        start = time.monotonic()
        s.sendall(b'S')
        left = n
        while left > 0:
            left -= s.send(block[:min(left, len(block))])
        s.shutdown(socket.SHUT_WR)
        reply = s.recv(64)
        out('sent', int(reply), '%.6f' % (time.monotonic() - start))


def hold(host, port):
    s = socket.create_connection((host, port), timeout=5)
    s.sendall(b'Ehi')
    assert s.recv(2) == b'hi'
    out('connected')
    for line in sys.stdin:
        words = line.split()
        s.settimeout(float(words[1]))
        try:
            data = s.recv(1)
            out('data' if data else 'closed')
        except socket.timeout:
            out('timeout')
        except ConnectionResetError:
            out('reset')


def tick():
    for _ in range(3000):          # a minute at most
        out('%.4f' % time.monotonic())
        time.sleep(0.02)


def daemon():
    if os.fork() == 0:
        os.setsid()
        if os.fork() == 0:
            out(os.getpid())
            time.sleep(60)
        os._exit(0)
    os.wait()


if __name__ == '__main__':
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == 'serve':
        serve(int(args[0]))
    elif cmd == 'probe':
        probe(args[0], int(args[1]), float(args[2]))
    elif cmd == 'send':
        send(args[0], int(args[1]), int(args[2]))
    elif cmd == 'hold':
        hold(args[0], int(args[1]))
    elif cmd == 'tick':
        tick()
    elif cmd == 'daemon':
        daemon()
