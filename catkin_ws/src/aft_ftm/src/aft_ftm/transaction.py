"""An adaptation's transaction: validate, plan, run the steps, roll back what was done.

Pure Python: no rospy, no processes, ``now`` always passed in. The transaction decides what
comes next (a :class:`Decision`); the caller (:mod:`aft_ftm.ros.adaptation_engine`) carries it
out and reports the outcome (:meth:`Transaction.ran`, :meth:`Transaction.undone`).

States (:class:`State`), every edge in :data:`EDGES` with its reason, one ``_change()``::

    VALIDATING --> VALIDATED --> RUNNING (group i of n) --> CLEANING_UP --> DONE
         |                          |   \\-------------------------------> DONE
         v                          v
      REFUSED                  ROLLING_BACK --> ROLLED_BACK | FAILED

Invariants:

- nothing is changed before RUNNING: a REFUSED script changed nothing;
- :attr:`Transaction.done` holds, in order, every step that may have changed something (a
  suspension that failed too: its answer may have been lost after its gate closed), with what
  undoing it needs; a rollback undoes them in reverse order (:func:`aft_ftm.adaptation.undo_plan`:
  bindings, promotions and killed nodes first, then every suspended node resumed, the launched
  nodes stopped last) and tries every undo, even after one failed;
- the run stops between groups of steps, never inside one: an interrupt (the ``adapt`` command's
  SIGINT or SIGTERM) or a lost suspension (its lease ran out) rolls back before the next group;
  a step that fails while interrupted is reported as interrupted;
- the group of the last resumes is the commit point: once one of its nodes is resumed, that site
  serves in the new configuration, and undoing the bindings would rebind it live (a request inside
  a stopped mechanism lost, review of stop 39). So a resume that fails while another of the group
  succeeded is not rolled back: it is reported (``resume_errors``, ok false, an alarm), and the node
  resumes when its lease runs out. Only a group none of whose resumes succeeded is rolled back (the
  engine fails them all, resuming none, when it finds the pause broken);
- once the last suspended node is resumed the new configuration serves (CLEANING_UP): what is
  left (the prepared order's kills) is cleanup; its failures are reported, never rolled back
  (undoing would rebind a live graph), and an interrupt leaves the rest undone;
- a rollback that could not undo everything ends FAILED, with :attr:`Transaction.alarm` naming
  what is left as it should not be.
"""
import collections
import enum

from . import adaptation
from .errors import AftError


class TransactionError(AftError):
    """A transaction was driven along an edge it does not have, or asked out of turn."""


class State(enum.Enum):
    VALIDATING = 0    # the script is being checked against the live graph; nothing changed
    VALIDATED = 1     # it fits: the plan is checked; nothing changed yet
    REFUSED = 2       # it does not fit (terminal): nothing changed
    RUNNING = 3       # running group ``index`` of the plan's groups
    CLEANING_UP = 4   # every suspended node resumed: the rest is cleanup, never rolled back
    ROLLING_BACK = 5  # undoing what was done, in reverse order
    DONE = 6          # every step run (cleanup failures reported) (terminal)
    ROLLED_BACK = 7   # every step done was undone (terminal)
    FAILED = 8        # the rollback itself failed: the system may not be as before (terminal; alarm)


TERMINAL = frozenset([State.REFUSED, State.DONE, State.ROLLED_BACK, State.FAILED])

EDGES = {
    (State.VALIDATING, State.VALIDATED): 'the script fits the live graph: the plan is checked, nothing changed',
    (State.VALIDATING, State.REFUSED): 'the script does not fit the live graph, or it cannot be checked: '
                                       'nothing changed',
    (State.VALIDATED, State.RUNNING): 'run: the first group of steps is next',
    (State.RUNNING, State.CLEANING_UP): 'every suspended node resumed: the new configuration serves; what is '
                                        'left is cleanup',
    (State.RUNNING, State.DONE): 'every step done',
    (State.RUNNING, State.ROLLING_BACK): 'a step failed, the run was interrupted, or a suspension was lost',
    (State.CLEANING_UP, State.DONE): 'cleanup over (its failures reported; an interrupt left the rest undone)',
    (State.ROLLING_BACK, State.ROLLED_BACK): 'every step done was undone',
    (State.ROLLING_BACK, State.FAILED): 'an undo failed: the system may not be as before the adaptation',
}


class Action(enum.Enum):
    RUN = 'run'       # run these steps (together): a failure rolls the adaptation back
    CLEAN = 'clean'   # run these cleanup steps (together): a failure is reported, the adaptation stands
    UNDO = 'undo'     # undo this one step, then report it with undone()
    END = 'end'       # the transaction is over (see its state)


Decision = collections.namedtuple('Decision', 'action steps opens_pause failure')
Decision.__doc__ = """What the caller does next. ``steps``: the steps to run together (RUN, CLEAN)
or the one undo step (UNDO). ``opens_pause``: the first suspension (the caller opens its
connections before it). ``failure``: on the first decision after the transaction turned to
rolling back, why (the caller says it); '' otherwise."""

Outcome = collections.namedtuple('Outcome', 'step started error info')
Outcome.__doc__ = """How one step ran: ``started`` (the caller's clock), ``error`` (None if it
succeeded, else why) and ``info`` (what undoing it needs: the previous binding, the launch, ...)."""


ABANDONED = 'call abandoned'   # how a step's error says its call got no answer in time (it may still take effect)
UNKNOWN = object()             # the undo info of such a step: what it replaced is not known


def stop_reason(interrupted, lost):
    """Why a run must stop and roll back now ('' if it goes on): an interrupt, or suspensions
    lost (node -> why it is no longer suspended)."""
    if interrupted:
        return 'interrupted (%s)' % interrupted
    if lost:
        return 'suspension lost: %s' % '; '.join('%s: %s' % item for item in sorted(lost.items()))
    return ''


class Transaction(object):
    """One adaptation, from validation to its end. Every state change goes through _change(),
    along EDGES. Not thread-safe: one caller drives it (the engine's run)."""

    def __init__(self, name, now):
        self.name = name
        self.state = State.VALIDATING
        self.reason = 'checking the script against the live graph'
        self.since = now
        self.history = []           # (now, from, to, reason)
        self.steps = []             # the plan
        self.groups = []            # the plan's groups of steps run together (adaptation.groups)
        self.cleanup_from = 0       # index of the first cleanup group (len(groups) if none)
        self.first_suspend = None   # index of the group that opens the pause (None: no pause)
        self.last_resume = None     # index of the group that closes it
        self.index = 0              # the next group to run (RUNNING, CLEANING_UP)
        self.pending = None         # the decision handed out and not yet reported on
        self.done = []              # (Step, undo info) of every step that may have changed something
        self.undo = []              # the undo plan (ROLLING_BACK)
        self.undo_index = 0         # the next undo step
        self.rollback = []          # {'action', 'target', 'ok', 'detail'} of each undo step
        self.cleanup_errors = []    # 'action target: why' of each cleanup step failed or left undone
        self.resume_errors = []     # 'resume target: why' of the last resumes that failed beside one that did not
        self.error = ''             # why it was rolled back
        self.interrupted = ''       # the interrupt acted on ('' if none)
        self.pause_start = None     # when the first suspension started (caller's clock)
        self.pause_end = None       # when the last suspended node was resumed (or the run ended)
        self._failure_untold = ''   # the rollback's cause, until a decision carries it

    # -- the one place where the state changes ------------------------------------------------
    def _change(self, state, now, reason):
        if (self.state, state) not in EDGES:
            raise TransactionError('adaptation %s: %s -> %s is not allowed (%s)'
                                   % (self.name, self.state.name, state.name, reason))
        self.history.append((now, self.state, state, reason))
        self.state, self.since, self.reason = state, now, reason
        if state in TERMINAL and self.pause_start is not None and self.pause_end is None:
            self.pause_end = now   # clients waited until the end

    def _expect(self, *states):
        if self.state not in states:
            raise TransactionError('adaptation %s: not allowed in state %s (expected %s)'
                                   % (self.name, self.state.name, ' or '.join(s.name for s in states)))

    # -- validation ---------------------------------------------------------------------------
    def validated(self, steps, now):
        """The script fits the live graph; steps is its plan (aft_ftm.adaptation.plan)."""
        self._expect(State.VALIDATING)
        self.steps = list(steps)
        self.groups = adaptation.groups(self.steps)
        # The cleanup steps are the plan's last ones; groups never straddle them (a resume comes before).
        first_cleanup = len(self.steps) - len(adaptation.cleanup_steps(self.steps))
        starts = [sum(len(g) for g in self.groups[:i]) for i in range(len(self.groups))]
        self.cleanup_from = next((i for i, start in enumerate(starts) if start >= first_cleanup), len(self.groups))
        suspends = [i for i, g in enumerate(self.groups) if g[0].action == 'suspend']
        resumes = [i for i, g in enumerate(self.groups) if g[0].action == 'resume']
        self.first_suspend = suspends[0] if suspends else None
        self.last_resume = resumes[-1] if resumes else None
        self._change(State.VALIDATED, now, '%d steps in %d groups' % (len(self.steps), len(self.groups)))

    def refused(self, why, now):
        self._change(State.REFUSED, now, why)

    def start(self, now):
        self._change(State.RUNNING, now, 'run: %d groups of steps' % len(self.groups))

    # -- running ------------------------------------------------------------------------------
    @property
    def progress(self):
        """'group i of n' (1-based) while it runs."""
        return 'group %d of %d' % (min(self.index + 1, len(self.groups)), len(self.groups))

    def next(self, now, interrupted='', lost=None):
        """What to do next, given the interrupt ('' if none) and the suspensions lost so far
        (node -> why). A decision must be reported on (ran(), undone()) before the next one."""
        if self.pending is not None:
            raise TransactionError('adaptation %s: the outcome of %s %s is not reported yet'
                                   % (self.name, self.pending.action.value, self._names(self.pending.steps)))
        if self.state is State.RUNNING:
            if self.index >= len(self.groups):
                self._change(State.DONE, now, EDGES[State.RUNNING, State.DONE])
            elif self.index >= self.cleanup_from:
                self._change(State.CLEANING_UP, now, EDGES[State.RUNNING, State.CLEANING_UP])
            else:
                group = self.groups[self.index]
                stop = stop_reason(interrupted, lost)
                if stop:
                    self._fail('%s before step %s %s' % (stop, group[0].action, group[0].target), interrupted, now)
                else:
                    return self._hand_out(Decision(Action.RUN, group, self.index == self.first_suspend, ''))
        if self.state is State.CLEANING_UP:
            if self.index < len(self.groups) and interrupted:
                self.interrupted = interrupted
                self.cleanup_errors += ['%s %s: not done (interrupted)' % (s.action, s.target)
                                        for group in self.groups[self.index:] for s in group]
                self.index = len(self.groups)
            if self.index >= len(self.groups):
                self._change(State.DONE, now, EDGES[State.CLEANING_UP, State.DONE])
            else:
                return self._hand_out(Decision(Action.CLEAN, self.groups[self.index], False, ''))
        if self.state is State.ROLLING_BACK:
            failure, self._failure_untold = self._failure_untold, ''
            if self.undo_index < len(self.undo):
                step = self.undo[self.undo_index]
                if step.action == 'stop_launch' and self.pause_end is None and self.pause_start is not None:
                    self.pause_end = now   # every node resumed: clients wait no longer
                return self._hand_out(Decision(Action.UNDO, [step], False, failure))
            failed = [r for r in self.rollback if not r['ok']]
            if failed:
                self._change(State.FAILED, now, 'could not undo %s' % '; '.join(
                    '%s %s (%s)' % (r['action'], r['target'], r['detail']) for r in failed))
            else:
                self._change(State.ROLLED_BACK, now, 'undid %d steps' % len(self.rollback))
            return Decision(Action.END, [], False, failure)
        if self.state in TERMINAL:
            return Decision(Action.END, [], False, '')
        raise TransactionError('adaptation %s: nothing to do in state %s' % (self.name, self.state.name))

    def _hand_out(self, decision):
        self.pending = decision
        return decision

    def ran(self, outcomes, now, interrupted=''):
        """The outcomes (Outcome, one per step) of the RUN or CLEAN decision handed out."""
        decision = self.pending
        if decision is None or decision.action not in (Action.RUN, Action.CLEAN):
            raise TransactionError('adaptation %s: no steps were handed out to run' % self.name)
        if len(outcomes) != len(decision.steps) or any(o.step not in decision.steps for o in outcomes):
            raise TransactionError('adaptation %s: outcomes of %s, but %s were handed out'
                                   % (self.name, self._names(o.step for o in outcomes), self._names(decision.steps)))
        self.pending = None
        self.index += 1
        if decision.action is Action.CLEAN:
            self.cleanup_errors += ['%s %s: %s' % (o.step.action, o.step.target, o.error)
                                    for o in outcomes if o.error is not None]
            return
        if decision.opens_pause and self.pause_start is None:
            self.pause_start = min(o.started for o in outcomes)
        for o in outcomes:
            if o.error is None or o.step.action == 'suspend':
                # A suspension that failed may still have closed the node's gate (its answer
                # lost): the rollback resumes it too, which is harmless on a running node.
                self.done.append((o.step, o.info))
            elif o.step.action in ('rebind', 'promote') and ABANDONED in o.error:
                # A call abandoned past its bound may still be carried out: its undo is asked for, with
                # nothing known of what it replaced (the rollback says so, never silent).
                self.done.append((o.step, UNKNOWN))
        failed = [o for o in outcomes if o.error is not None]
        if failed and len(failed) < len(outcomes) and self.index - 1 == self.last_resume:
            # Committed: a site of the group serves in the new configuration (see the invariants).
            self.resume_errors += ['%s %s: %s' % (o.step.action, o.step.target, o.error) for o in failed]
            self.error = 'the last resumes partly failed (the adaptation stands): %s' % '; '.join(self.resume_errors)
            self.pause_end = now
        elif failed:
            first = failed[0]
            if interrupted:
                error = 'interrupted (%s) during step %s %s' % (interrupted, first.step.action, first.step.target)
            else:
                error = 'step %s %s failed: %s' % (first.step.action, first.step.target, first.error)
            self._fail(error, interrupted, now)
        elif self.index - 1 == self.last_resume:
            self.pause_end = now

    def _fail(self, error, interrupted, now):
        self.error, self.interrupted = error, interrupted
        self.undo = adaptation.undo_plan(self.done)
        self.undo_index = 0
        self._failure_untold = error
        self._change(State.ROLLING_BACK, now, error)

    def undone(self, step, ok, detail, now):
        """The outcome of the UNDO decision handed out: ok, and what was done or why it failed."""
        decision = self.pending
        if decision is None or decision.action is not Action.UNDO or decision.steps[0] != step:
            raise TransactionError('adaptation %s: %s %s was not handed out to undo' % (self.name, step.action,
                                                                                       step.target))
        self.pending = None
        self.undo_index += 1
        self.rollback.append({'action': step.action, 'target': step.target, 'ok': bool(ok), 'detail': detail})

    # -- the outcome --------------------------------------------------------------------------
    @property
    def ok(self):
        return self.state is State.DONE   # (with resume_errors: it stands, and the alarm says what failed)

    @property
    def rolled_back(self):
        return self.state in (State.ROLLED_BACK, State.FAILED)

    @property
    def pause_s(self):
        if self.pause_start is None:
            return 0.0
        return (self.pause_end if self.pause_end is not None else self.since) - self.pause_start

    @property
    def alarm(self):
        """'' unless the rollback failed, or a last resume failed beside one that did not, or a retired node
        could not be stopped; then what is left as it should not be (an alarm's text)."""
        if self.state is State.DONE and (self.resume_errors or self.cleanup_errors):
            said = []
            if self.resume_errors:
                said.append('%s: a node not resumed resumes by itself when its lease runs out; one whose suspension '
                            'had ended ran during the rebinds (requests then may have been lost or executed twice)'
                            % '; '.join(self.resume_errors))
            if self.cleanup_errors:   # (said in the report only, before: the old node ran on unsaid; review of
                said.append('what it retires was not all stopped (%s): it runs on beside the new nodes, and its '
                            'name cannot be launched again until it is' % '; '.join(self.cleanup_errors))
            return 'adaptation %s: the new configuration serves, but %s' % (self.name, '; and '.join(said))   # s. 48)
        if self.state is not State.FAILED:
            return ''
        failed = ['%s %s (%s)' % (r['action'], r['target'], r['detail']) for r in self.rollback if not r['ok']]
        return ('adaptation %s: rolled back after "%s", but the rollback failed: could not %s; the system may '
                'not be as before the adaptation' % (self.name, self.error, '; '.join(failed)))

    def summary(self):
        """The transaction's part of the engine's report (JSON-ready)."""
        out = {'ok': self.ok, 'error': self.error, 'interrupted': self.interrupted, 'rolled_back': self.rolled_back,
               'cleanup_errors': list(self.cleanup_errors), 'resume_errors': list(self.resume_errors),
               'pause_s': self.pause_s, 'state': self.state.name,
               'alarm': self.alarm}
        if self.rolled_back:
            out['rollback'] = [dict(r) for r in self.rollback]
        return out

    @staticmethod
    def _names(steps):
        return ', '.join('%s %s' % (s.action, s.target) for s in steps)
