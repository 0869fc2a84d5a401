"""What a replica's Recovery node does when its crash detector declares the peer failed."""
import enum

from .protocol import Role


class Step(enum.Enum):
    FAIL_SILENCE = 'kill whatever is left of the failed site'
    PROMOTE_AFTER = "fence the After against the old primary's checkpoints and make it ALONE"
    PROMOTE_PROTOCOL = "make the Protocol ALONE once it stored every checkpointed reply"
    BIND_CLIENT = "bind the Protocol to the clients' request and reply topics"
    AFTER_ALONE = 'stop checkpointing: release the replies held for the lost backup'


# What each step must wait for. Binding the clients' topic early is safe: a Protocol that is
# still a backup queues the requests it receives (answering only those whose checkpointed reply
# it holds). The Protocol executes them only once promoted, and it is promoted only once the
# failed site is silent (no two primaries) and its After is fenced against the old primary.
PREREQUISITES = {
    Step.FAIL_SILENCE: (),
    Step.PROMOTE_AFTER: (),
    Step.BIND_CLIENT: (),
    Step.PROMOTE_PROTOCOL: (Step.FAIL_SILENCE, Step.PROMOTE_AFTER),
    Step.AFTER_ALONE: (),
}


def plan(role):
    """The steps when the peer of a replica in ``role`` has failed, as waves: the steps of a
    wave run in parallel, each wave once the previous one is complete."""
    if role == Role.BACKUP:
        steps = [Step.FAIL_SILENCE, Step.PROMOTE_AFTER, Step.BIND_CLIENT, Step.PROMOTE_PROTOCOL]
    elif role == Role.PRIMARY:
        steps = [Step.FAIL_SILENCE, Step.AFTER_ALONE]
    else:
        steps = []   # ALONE: nobody left to lose
    return waves(steps)


def waves(steps):
    """Group steps into waves that respect PREREQUISITES (each step in the earliest wave possible)."""
    done, result, left = set(), [], list(steps)
    while left:
        wave = [s for s in left if all(p in done or p not in steps for p in PREREQUISITES[s])]
        if not wave:
            raise ValueError('circular prerequisites among %s' % left)
        result.append(wave)
        done.update(wave)
        left = [s for s in left if s not in wave]
    return result


def role_after(role):
    """The replica's role once the plan for its peer's failure is carried out."""
    return Role.ALONE if role in (Role.BACKUP, Role.PRIMARY) else role


def same_process(create_time, last_heard_wall, tolerance=0.05):
    """True if a process created at create_time could have sent a heartbeat at last_heard_wall.

    Guards fail-silence against a pid reused by an unrelated process after the site died.
    """
    return create_time <= last_heard_wall + tolerance
