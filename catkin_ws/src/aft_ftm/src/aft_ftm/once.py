"""What a node remembers so that a second copy of a message is not acted on twice.

A request is sent on once by the stage before, but a copy can come again: a publisher heard on two
connections across a rebind, or a message published again by anyone on the graph. Where acting on
it twice would run it twice (an LFR follower computing a forward, TR's Before saving a state and
executing), the node remembers the keys it acted on, the last ``remember`` of them; TR's Before also
keeps the answers it can give such a copy again (KeptAnswers).
"""
import collections


class RecentKeys(object):
    """The last ``remember`` keys added, the oldest forgotten first."""

    def __init__(self, remember=65536):
        self.remember = remember
        self._keys = collections.OrderedDict()

    def __contains__(self, key):
        return key in self._keys

    def __len__(self):
        return len(self._keys)

    def add(self, key):
        """Remember key; False if it was remembered already (a second copy), True if it is new."""
        if key in self._keys:
            return False
        self._keys[key] = True
        while len(self._keys) > self.remember:
            self._keys.popitem(last=False)
        return True

    def discard(self, key):
        """Forget key (what it stood for did not happen: a copy may act on it)."""
        self._keys.pop(key, None)


def answer_size(reply):
    """What a kept answer costs, counted against KeptAnswers' byte bound: its payload and error text."""
    return len(reply.payload) + len(reply.error) + 64


class KeptAnswers(object):
    """The answers given to the last keys, so that a second copy of a request gets its answer again
    (a Protocol started again lost the first): at most ``remember`` of them, and at most ``max_bytes``
    of payload and error text (None: no byte bound), the oldest forgotten first (a copy of a
    forgotten one gets none). An answer larger than ``max_bytes`` is not kept: it would have pushed
    out every other (review of session 39)."""

    def __init__(self, remember=65536, max_bytes=8 * 2 ** 20):
        self.remember, self.max_bytes = remember, max_bytes
        self.bytes = 0
        self._answers = collections.OrderedDict()

    def __len__(self):
        return len(self._answers)

    def get(self, key):
        return self._answers.get(key)

    def keep(self, key, reply):
        """Keep reply as key's answer; False if it is too large to be kept."""
        old = self._answers.pop(key, None)
        if old is not None:
            self.bytes -= answer_size(old)
        if self.max_bytes is not None and answer_size(reply) > self.max_bytes:
            return False
        self._answers[key] = reply
        self.bytes += answer_size(reply)
        while self._answers and (len(self._answers) > self.remember or
                                 self.max_bytes is not None and self.bytes > self.max_bytes):
            _, gone = self._answers.popitem(last=False)
            self.bytes -= answer_size(gone)
        return True
