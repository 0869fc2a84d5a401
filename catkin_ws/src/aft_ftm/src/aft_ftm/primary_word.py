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
- a word naming no node is refused aloud (taken, it would open the car to any sender).
"""
import enum


class Word(enum.Enum):
    TAKEN = 'taken'                 # a new primary (or the first word)
    ADOPTED = 'adopted'             # another run naming the board in force: its run followed from now on
    DUPLICATE = 'duplicate'         # the word in force again: nothing to say
    PASSED = 'primary_ignored'      # an earlier term, the same term naming another board, or no node named
    DISPUTED = 'primary_disputed'   # another run naming another board than the one in force

    @property
    def refused(self):
        return self in (Word.PASSED, Word.DISPUTED)


class PrimaryWord(object):
    """What a consumer holds of the watchdog's word: the board in force, its term and run."""

    def __init__(self):
        self.board = None
        self.term = 0
        self.run = None
        self.refused = 0

    def hear(self, board, term, run, names_nodes=True):
        """The word naming ``board`` the primary in ``term`` of run ``run``; ``names_nodes``: whether it
        names the board's nodes. Returns a :class:`Word` (see the module)."""
        if not names_nodes:
            verdict = Word.PASSED
        elif self.run is None or (run == self.run and term > self.term):
            verdict = Word.TAKEN
        elif run == self.run:
            verdict = Word.DUPLICATE if (term, board) == (self.term, self.board) else Word.PASSED
        elif board == self.board:
            verdict = Word.ADOPTED
        else:
            verdict = Word.DISPUTED
        if verdict in (Word.TAKEN, Word.ADOPTED):
            self.board, self.term, self.run = board, term, run
        elif verdict.refused:
            self.refused += 1
        return verdict

    def describe(self):
        return ('board %s, term %d of watchdog run %s' % (self.board, self.term, self.run) if self.run is not None
                else 'no word heard yet')
