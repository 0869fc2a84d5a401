"""What a node remembers so that a second copy of a message is not acted on twice.

A request is sent on once by the stage before, but a copy can come again: a publisher heard on two
connections across a rebind, or a message published again by anyone on the graph. Where acting on
it twice would run it twice (an LFR follower computing a forward, TR's Before saving a state and
executing), the node remembers the keys it acted on, the last ``remember`` of them.
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
