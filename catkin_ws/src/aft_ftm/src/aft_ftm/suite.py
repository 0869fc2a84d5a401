"""Which cases of a family the short test suite runs (``make test``; ``make test-full`` runs them all).

The suite must stay within 30 minutes on a 2-core machine. Many live tests come in families: the
same guarantee under variants of one fault (the two orders of an adaptation, each FMECA row of one
mechanism, a site frozen or answering). The short suite runs ``keep`` members of each family, drawn
from a seed: every family, and so every mechanism and guarantee, is exercised in every run, and over
runs every member is. The seed is printed (``AFT_SUITE_SEED``, shared by pytest and the rostests it
starts); the same seed draws the same members; ``AFT_SUITE=full`` runs every member. A member not
drawn is reported as skipped, naming its family, the seed and how to run it: never silent.

Plain Python, no ROS.
"""
import os
import random
import time

FULL = 'full'
SHORT = 'short'
SUITES = (SHORT, FULL)


def suite(environ=None):
    """The suite asked for: AFT_SUITE, 'short' by default. Anything else is refused, naming it."""
    value = (environ if environ is not None else os.environ).get('AFT_SUITE', SHORT) or SHORT
    if value not in SUITES:
        raise ValueError('AFT_SUITE=%r: expected one of %s' % (value, ', '.join(SUITES)))
    return value


def seed(environ=None):
    """The draw's seed: AFT_SUITE_SEED, or one made from the time, which is then put in the environment
    (the processes started after share it). A seed that is not a whole number is refused."""
    environ = environ if environ is not None else os.environ
    text = environ.get('AFT_SUITE_SEED', '')
    if not text:
        text = str(int(time.time()) % 100000)
        environ['AFT_SUITE_SEED'] = text
    try:
        return int(text)
    except ValueError:
        raise ValueError('AFT_SUITE_SEED=%r: expected a whole number' % text)


def drawn(family, members, keep, seed_value, which=SHORT):
    """The members of ``family`` the suite runs: all in the full suite or when ``keep`` covers them, else
    ``keep`` of them drawn from the seed and the family's name (the members' order does not matter)."""
    members = sorted(set(members))
    if keep < 1:
        raise ValueError('family %s: keep must be at least 1, got %r' % (family, keep))
    if which == FULL or keep >= len(members):
        return set(members)
    return set(random.Random('%d/%s' % (seed_value, family)).sample(members, keep))


def not_drawn(family, keep, count, seed_value):
    """Why a member is skipped, for the test report."""
    return ('not drawn in the short suite: family %s runs %d of its %d members this time (AFT_SUITE_SEED=%d '
            'draws the same; AFT_SUITE=full, or make test-full, runs every one)' % (family, keep, count, seed_value))


NOT_DRAWN_FILE = 'not_drawn.txt'


def say_not_drawn(case_name, why, environ=None):
    """A case not drawn, said on the output and, under a test runner that collects results
    (AFT_RESULTS_DIR: tests/integration/test_rostest.py), in its file there: rostest's summary counts a
    skipped case as passed."""
    print('AFT_SUITE_SKIPPED %s: %s' % (case_name, why), flush=True)
    folder = (environ if environ is not None else os.environ).get('AFT_RESULTS_DIR')
    if folder:
        os.makedirs(folder, exist_ok=True)
        with open(os.path.join(folder, NOT_DRAWN_FILE), 'a') as f:
            f.write(case_name + '\n')


class Families(object):
    """Members declared by name, family by family (the rostest scripts declare theirs as their class is
    read), and the draw made once all are known."""

    def __init__(self):
        self.members = {}   # family -> (keep, [member names])

    def add(self, family, keep, member):
        known = self.members.setdefault(family, (keep, []))
        if known[0] != keep:
            raise ValueError('family %s declared with keep %d and %d' % (family, known[0], keep))
        known[1].append(member)

    def family_of(self, member):
        for family, (keep, names) in self.members.items():
            if member in names:
                return family, keep, names
        return None

    def skip_reason(self, member, environ=None):
        """None if member runs in this suite, else why not (a member of no family always runs)."""
        found = self.family_of(member)
        if found is None:
            return None
        family, keep, names = found
        which, value = suite(environ), seed(environ)
        if member in drawn(family, names, keep, value, which):
            return None
        return not_drawn(family, keep, len(names), value)
