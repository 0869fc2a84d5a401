"""Incremental checkpoints (aft_ftm.delta): random states and changes, drawn from a printed seed."""
import random
import time

import pytest

from aft_ftm.delta import DeltaDecoder, DeltaEncoder, DeltaError, apply, encode


def mutate(rng, state):
    """A random change: bytes overwritten in place here and there, an append, a cut, an insertion."""
    state = bytearray(state)
    kind = rng.choice(['overwrite', 'overwrite', 'append', 'truncate', 'insert', 'none'])
    if kind == 'overwrite' and state:
        for _ in range(rng.randint(1, 5)):
            at = rng.randrange(len(state))
            piece = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 40)))
            state[at:at + len(piece)] = piece[:len(state) - at]
    elif kind == 'append':
        state += bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 300)))
    elif kind == 'truncate' and state:
        del state[rng.randrange(len(state)):]
    elif kind == 'insert':
        at = rng.randint(0, len(state))
        state[at:at] = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 100)))
    return bytes(state)


def test_any_change_rebuilds_exactly_the_new_state():
    seed = int(time.time())
    rng = random.Random(seed)
    for case in range(400):
        base = bytes(rng.getrandbits(8) for _ in range(rng.choice([0, 1, 63, 64, 65, 4095, 4096, 4097, 9000])))
        new = mutate(rng, base)
        assert apply(base, encode(base, new)) == new, 'seed %d, case %d' % (seed, case)


def test_a_stream_of_checkpoints_of_a_large_state_costs_its_changes_not_its_size():
    seed = int(time.time())
    rng = random.Random(seed)
    state = bytes(rng.getrandbits(8) for _ in range(1 << 20))
    encoder, decoder = DeltaEncoder(), DeltaDecoder()
    sizes = []
    for step in range(30):
        buf = bytearray(state)
        at = rng.randrange(len(buf) - 100)
        buf[at:at + 100] = bytes(rng.getrandbits(8) for _ in range(100))   # ~100 bytes change per request
        state = bytes(buf)
        payload, is_delta = encoder.next(state)
        assert is_delta == (step > 0), 'seed %d' % seed   # the first has no base: sent whole
        rebuilt = decoder.state(payload, is_delta)
        assert rebuilt == state, 'seed %d, step %d' % (seed, step)
        decoder.accept(rebuilt)
        sizes.append(len(payload))
    assert max(sizes[1:]) < 2048, (seed, sizes)   # issue 18: under 2 KB per request for a 1 MB state


def test_a_delta_against_another_base_or_corrupt_is_refused_by_name_and_changes_nothing():
    base = bytes(range(256)) * 40
    new = base[:500] + b'changed' + base[507:]
    delta = encode(base, new)
    with pytest.raises(DeltaError, match='the state held has'):
        apply(base[:-1] + b'x', delta)
    corrupt = bytearray(delta)
    corrupt[-3] ^= 0xff
    with pytest.raises(DeltaError, match='does not match'):
        apply(base, bytes(corrupt))
    with pytest.raises(DeltaError, match='truncated|out of bounds|after its last run'):
        apply(base, delta[:-10])
    with pytest.raises(DeltaError, match='not a state delta'):
        apply(base, b'garbage')
    decoder = DeltaDecoder()
    with pytest.raises(DeltaError, match='holds no state'):
        decoder.state(delta, True)
    decoder.accept(base)
    with pytest.raises(DeltaError):
        decoder.state(bytes(corrupt), True)
    assert decoder.base == base and decoder.state(delta, True) == new


def test_small_states_and_large_changes_are_sent_whole():
    encoder = DeltaEncoder(min_size=1024)
    encoder.next(b'a' * 100)
    assert encoder.next(b'b' * 100) == (b'b' * 100, False)           # under min_size
    encoder.next(bytes(4096))
    payload, is_delta = encoder.next(bytes(range(256)) * 16)         # every byte changed
    assert not is_delta and len(payload) == 4096
