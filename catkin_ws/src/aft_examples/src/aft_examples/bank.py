"""The demo application's logic: a bank account that makes request errors visible.

Every operation extends a hash chain, so the reply to a request (balance, count,
digest) is correct only if every earlier request was applied exactly once and in
order: a lost request shows in ``count``, a duplicated one in ``balance`` and
``count``, a reordered one in ``digest``.
"""
import collections
import hashlib
import json
import zlib

from aft_ftm.delta import ServerChanges
from aft_ftm.errors import StateError

GENESIS = '0' * 16
OPERATIONS = ('deposit', 'withdraw')


class InsufficientFunds(Exception):
    """A withdrawal larger than the balance (an application error, replied as such)."""


class Account(object):
    def __init__(self, balance=0, count=0, digest=GENESIS):
        self.balance = balance
        self.count = count
        self.digest = digest

    def apply(self, op, amount, tag=''):
        """Apply one operation; returns (balance, count, digest). Raises ValueError or InsufficientFunds.
        A tag, if given, enters the hash chain with the operation (an untagged chain is unchanged)."""
        if op not in OPERATIONS:
            raise ValueError('unknown operation %r (known: %s)' % (op, ', '.join(OPERATIONS)))
        if amount < 0:
            raise ValueError('amount must be >= 0, got %d' % amount)
        if op == 'withdraw' and amount > self.balance:
            raise InsufficientFunds('cannot withdraw %d from a balance of %d' % (amount, self.balance))
        self.balance += amount if op == 'deposit' else -amount
        self.count += 1
        link = ('%s|%s:%d' % (self.digest, op, amount) + (':' + tag if tag else '')).encode()
        self.digest = hashlib.sha256(link).hexdigest()[:16]
        return self.balance, self.count, self.digest

    def snapshot(self):
        return self.balance, self.count, self.digest

    # -- state-manager encoding -------------------------------------------------
    def get_state(self):
        return json.dumps({'balance': self.balance, 'count': self.count, 'digest': self.digest},
                          sort_keys=True).encode()

    def set_state(self, data):
        """Replace the state; a malformed state raises StateError and changes nothing."""
        try:
            state = json.loads(bytes(data).decode())
        except (ValueError, UnicodeDecodeError) as e:
            raise StateError('account state is not valid JSON: %s' % e)
        if not isinstance(state, dict) or set(state) != {'balance', 'count', 'digest'}:
            raise StateError('account state must have exactly balance, count, digest; got %r' % (state,))
        balance, count, digest = state['balance'], state['count'], state['digest']
        if not isinstance(balance, int) or isinstance(balance, bool) or balance < 0:
            raise StateError('account state balance must be an integer >= 0, got %r' % (balance,))
        if not isinstance(count, int) or isinstance(count, bool) or count < 0:
            raise StateError('account state count must be an integer >= 0, got %r' % (count,))
        if not isinstance(digest, str) or len(digest) != 16:
            raise StateError('account state digest must be 16 hex characters, got %r' % (digest,))
        self.balance, self.count, self.digest = balance, count, digest


class StateLayout(object):
    """The bank server's state as its state manager gives it: ``ballast_bytes`` of inert ballast and a
    0 byte (none without ballast), then the account's encoding. The ballast never changes, so the server
    knows what changed since any version it named: one run, the account. Its CRC continues the
    ballast's, computed once: telling the changes costs the account's size, not the state's.

    Versions are ``<incarnation>:<changes>``; the account's length is remembered for the last ``KNOWN``
    versions named, and a version not among them (forgotten, another incarnation's) gets the whole state.
    """
    KNOWN = 64

    def __init__(self, ballast_bytes, incarnation):
        self.prefix = b'\xa5' * ballast_bytes + b'\0' if ballast_bytes else b''
        self.prefix_crc = zlib.crc32(self.prefix)
        self.incarnation = incarnation
        self.changes = 0
        self.known = collections.OrderedDict()   # version -> length of the account's encoding at it

    def state(self, account):
        return self.prefix + account

    def account(self, state):
        """The account's encoding in a whole state; StateError if its ballast is not this server's length."""
        state = bytes(state)
        if not self.prefix:
            return state
        ballast, _, account = state.rpartition(b'\0')
        if len(ballast) != len(self.prefix) - 1:
            raise StateError('state ballast of %d bytes, expected %d' % (len(ballast), len(self.prefix) - 1))
        return account

    def changed(self):
        """An operation applied or a state set: the state has a new version."""
        self.changes += 1

    def since(self, version, account):
        """ServerChanges from ``version`` to the state whose account encodes as ``account``."""
        now = '%s:%d' % (self.incarnation, self.changes)
        old = self.known.get(version)
        self.known[now] = len(account)
        self.known.move_to_end(now)
        while len(self.known) > self.KNOWN:
            self.known.popitem(last=False)
        if old is None:
            return ServerChanges(now, state=self.state(account))
        start = len(self.prefix)
        return ServerChanges(now, runs=[(start, start + old, account)], size=start + len(account),
                             crc=zlib.crc32(account, self.prefix_crc) & 0xffffffff)


def account_state(state):
    """The account's encoding in a bank server's whole state, without its ballast if any."""
    return bytes(state).rpartition(b'\0')[2]


# The bank demo's assertions as arguments of the compose adaptation script (mechanism:=ad).
AD_ARGS = ['mechanism:=ad', 'request_assertions:=[aft_examples.bank:amount_within_limit]',
           'reply_assertions:=[aft_examples.bank:balance_never_negative]']


def operation(i):
    """The i-th operation of the demo workload (deterministic, varied, never overdrawn)."""
    if i % 5 == 4:
        return 'withdraw', 1 + (i * 7) % 5
    return 'deposit', 1 + (i * 13) % 10


class ReplyChecker(object):
    """The client's model of the account: classifies every reply against it."""

    def __init__(self):
        self.model = Account()
        self.correct = 0
        self.lost = 0          # the server had applied fewer operations than sent
        self.duplicated = 0    # the server had applied more operations than sent
        self.reordered = 0     # right count, wrong hash chain
        self.errors = 0        # error replies or failed calls

    def expect(self, op, amount):
        return self.model.apply(op, amount)

    def check(self, expected, got):
        """Compare a reply (balance, count, digest) with the expectation; resynchronise on a mismatch."""
        if tuple(got) == tuple(expected):
            self.correct += 1
            return True
        if got[1] < expected[1]:
            self.lost += expected[1] - got[1]
        elif got[1] > expected[1]:
            self.duplicated += got[1] - expected[1]
        else:
            self.reordered += 1
        self.model = Account(*got)
        return False

    def summary(self):
        return {'correct': self.correct, 'lost': self.lost, 'duplicated': self.duplicated,
                'reordered': self.reordered, 'errors': self.errors}


# -- example safety assertions for Assertion & Duplex (named bank:... in launch files) ------------
LIMIT = 1000


def amount_within_limit(request):
    """Request assertion: no single operation moves more than LIMIT."""
    return request.amount <= LIMIT or 'amount %d is over the limit of %d' % (request.amount, LIMIT)


def balance_never_negative(request, response):
    """Reply assertion: an account is never overdrawn."""
    return response.balance >= 0 or 'balance %d is negative' % response.balance
