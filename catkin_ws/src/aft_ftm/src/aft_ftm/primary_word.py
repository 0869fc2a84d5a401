"""The watchdog's word on which board of a replicated pub/sub node is the primary
(aft_msgs/PrimaryBoard), as each consumer follows it, without rospy.

The watchdog says it at its start and after each take-over, with a term one more each time, in a run
of its own (``incarnation``). The consumers (the car's commandManager, each board's After) follow it by
one rule, :meth:`PrimaryWord.hear`:

- the first word heard is taken, whatever its run and term (a consumer started after a take-over
  must hear of it);
- in the run followed, a later term is taken; the word in force heard again (a latched word re-sent
  when a subscriber connects again) changes nothing, silently; an earlier term, or the same term
  naming another board, is refused aloud (reordered, replayed or forged);
- another run's word (a watchdog started again, which starts from its configured primary whatever
  board drives; an old watchdog's word delivered late) is followed from then on only if it names the
  board in force: its run is adopted, nothing changes. Naming another board it is refused aloud, so
  that no restart of the watchdog deposes the board that drives;
- a run left (another adopted since) is never followed again: its words are refused aloud. Adopted
  again by a late word naming the board in force, it left the consumer refusing every later term of
  the run that replaced it (review of session 51). Runs say when they started (the incarnation
  ``START:PID:ID``): a word of a run older than the one followed is refused, never adopted (a late
  word of an old run had locked out the live one for good; review of session 52);
- a word naming no node is refused aloud (taken, it would open the car to any sender).

What the first word heard means is the consumer's to say: a board's After started again must not take
a word older than the role the watchdog gave it (see aft_ftm.cycle_replica.CycleReplica.primary_named).
"""
import collections
import enum


class Word(enum.Enum):
    TAKEN = 'taken'                 # a new primary (or the first word)
    ADOPTED = 'adopted'             # another run naming the board in force: its run followed from now on
    DUPLICATE = 'duplicate'         # the word in force again: nothing to say
    PASSED = 'primary_ignored'      # an earlier term, the same term naming another board, a run left, or no node
    DISPUTED = 'primary_disputed'   # another run naming another board than the one in force

    @property
    def refused(self):
        return self in (Word.PASSED, Word.DISPUTED)


def run_started(run):
    """When a watchdog run started (s since the epoch, the first field of its incarnation
    ``START:PID:ID``), or None if the incarnation does not say."""
    parts = str(run).split(':')
    try:
        return float(parts[0]) if len(parts) == 3 else None
    except ValueError:
        return None


def _older(run, than):
    """Whether watchdog run ``run`` started before run ``than`` (both saying when)."""
    started, other = run_started(run), run_started(than)
    return started is not None and other is not None and started < other


class PrimaryWord(object):
    """What a consumer holds of the watchdog's word: the board in force, its term and run."""

    RUNS_LEFT_KEPT = 16   # the runs left, remembered (a watchdog restarted more often than this is an alarm anyway)

    def __init__(self):
        self.board = None
        self.term = 0
        self.run = None
        self.refused = 0
        self.why = ''   # why the last word heard was refused
        self.left = collections.OrderedDict()   # runs followed once and left since (oldest first)

    def hear(self, board, term, run, names_nodes=True):
        """The word naming ``board`` the primary in ``term`` of run ``run``; ``names_nodes``: whether it
        names the board's nodes. Returns a :class:`Word` (see the module)."""
        self.why = ''
        if not names_nodes:
            verdict, self.why = Word.PASSED, 'it names no node'
        elif run in self.left:
            verdict, self.why = Word.PASSED, 'its watchdog run was left for a later one'
        elif self.run is None or (run == self.run and term > self.term):
            verdict = Word.TAKEN
        elif run == self.run:
            verdict = Word.DUPLICATE if (term, board) == (self.term, self.board) else Word.PASSED
            if verdict is Word.PASSED:
                self.why = 'a term passed' if term < self.term else 'the term in force naming another board'
        elif _older(run, self.run):
            verdict, self.why = Word.PASSED, 'an earlier watchdog run than the one followed'
        elif board == self.board:
            verdict = Word.ADOPTED
        else:
            verdict, self.why = Word.DISPUTED, 'another watchdog run than the one followed names another board'
        if verdict in (Word.TAKEN, Word.ADOPTED):
            if self.run is not None and run != self.run:
                self.left[self.run] = True
                while len(self.left) > self.RUNS_LEFT_KEPT:
                    self.left.popitem(last=False)
            self.board, self.term, self.run = board, term, run
        elif verdict.refused:
            self.refused += 1
        return verdict

    def describe(self):
        return ('board %s, term %d of watchdog run %s' % (self.board, self.term, self.run) if self.run is not None
                else 'no word heard yet')
