"""The link monitor's measurement (aft_ftm.link_probe): the wire format, the sink's clock, the
median, and a real probe over the loopback."""
import random
import socket
import statistics

import pytest

from aft_ftm.errors import ConfigError
from aft_ftm.link_probe import (Estimator, Measure, ProbeError, Sink, check_endpoint, parse_answer, probe, rate,
                                PROBE_HEADER)


@pytest.mark.parametrize('value', ['', 'host', 'host:', ':80', 'host:0', 'host:70000', 'a:b:1', 'host:8x', 5])
def test_a_bad_endpoint_is_refused_naming_the_parameter(value):
    with pytest.raises(ConfigError, match='~peer/endpoint'):
        check_endpoint('~peer/endpoint', value)


def test_an_endpoint_is_host_and_port():
    assert check_endpoint('p', '10.213.4.11:4567') == ('10.213.4.11', 4567)


@pytest.mark.parametrize('line', ['', 'AFTSINK 1', 'AFTSINK 2 10 0.1', 'HTTP/1.1 200 OK', 'AFTSINK 1 ten 0.1',
                                  'AFTSINK 1 10 -1', 'AFTSINK 1 -5 0.1', 'AFTSINK 1 10 nan'])
def test_a_malformed_answer_is_an_error_naming_it(line):
    with pytest.raises(ProbeError, match='answer'):
        parse_answer(line)


def test_the_sink_clock_starts_once_the_burst_is_through():
    m = Measure(skip=1000)
    m.add(600, 0.0)
    m.add(600, 0.001)      # the burst: 1200 bytes at once start the clock
    m.add(1000, 1.001)
    m.add(1000, 2.001)
    assert m.result() == (2000, 2.0)
    assert rate(*m.result()) == 1000.0


def test_a_probe_that_fits_in_the_burst_measures_nothing():
    m = Measure(skip=10000)
    m.add(5000, 0.0)
    assert m.result() == (0, 0.0) and rate(*m.result()) is None


def test_the_estimate_is_the_median_of_the_last_probes_and_failures_are_counted():
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    e = Estimator(window=3)
    assert e.estimate() is None
    samples = [rng.uniform(1e3, 1e7) for _ in range(20)]
    for i, s in enumerate(samples):
        e.add(s)
        last = samples[max(0, i - 2):i + 1]
        assert e.estimate() == statistics.median(last), 'seed %d' % seed
    e.add(None)
    e.add(None)
    assert e.failures == 2 and e.estimate() == sorted(samples[-3:])[1]
    e.add(5.0)
    assert e.failures == 0
    with pytest.raises(ConfigError):
        Estimator(window=0)


def test_a_probe_over_the_loopback_measures_a_rate():
    sink = Sink('127.0.0.1', skip=1024).start()
    try:
        count, seconds = probe(sink.endpoint, seconds=0.05, max_bytes=2 << 20)
        assert count > 0 and seconds > 0
        assert rate(count, seconds) > 1e6     # the loopback carries far more than 1 MB/s
        assert sink.served == 1
    finally:
        sink.close()


def test_a_sink_refuses_what_is_not_a_probe_and_goes_on():
    sink = Sink('127.0.0.1').start()
    try:
        with socket.create_connection(sink.endpoint, timeout=2) as s:
            try:
                s.sendall(b'GET / HTTP/1.0\r\n\r\n')
                s.shutdown(socket.SHUT_WR)
                answer = s.recv(100)
            except OSError:                    # the sink closed it first (reset, not connected)
                answer = b''
            assert answer == b''               # nothing answered
        count, _ = probe(sink.endpoint, seconds=0.02, max_bytes=1 << 20)
        assert count > 0
        assert len(sink.refused) == 1 and 'not a probe' in sink.refused[0]
        assert PROBE_HEADER.startswith(b'AFTPROBE')
    finally:
        sink.close()


def test_a_probe_of_nobody_is_an_error_naming_the_address():
    s = socket.socket()
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()      # nothing listens there now
    with pytest.raises(ProbeError, match='127.0.0.1:%d' % port):
        probe(('127.0.0.1', port), seconds=0.01, timeout=1.0)
