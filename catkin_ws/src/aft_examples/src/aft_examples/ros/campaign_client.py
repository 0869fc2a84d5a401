"""A campaign client: random bank operations through its own Proxy, each call written to a history
file as it starts and as it ends (aft_examples.history.read_history reads it)."""
import json
import os
import random
import time

import rospy

from aft_ftm import config
from aft_ftm.ros.params import param
from aft_examples.history import classify_error
from aft_examples.ros.bank_nodes import account_proxy


class CampaignClientNode(object):
    """Calls its service with random deposits and withdrawals, one at a time, until ~stop_file exists.

    Every operation carries a unique tag (``<client>:<index>``) that enters the account's hash chain,
    so that the history checker tells every execution apart. A call is written to ~history (JSON
    lines) when it starts and when it ends, so a call in flight when the client dies is seen.

    Parameters:
        ~history (str, required): the history file (appended).
        ~stop_file (str, required): the client stops once this file exists (after its call ends).
        ~seed (int, 0): seeds the operations.
        ~pause (float, 0.02 s): between calls; also the wait after a call that could not be sent.
    Services called:
        account (aft_msgs/Account): remap it to this client's Proxy.
    """

    def __init__(self):
        self.history = param('history', config.non_empty_str, required=True)
        self.stop_file = param('stop_file', config.non_empty_str, required=True)
        self.rng = random.Random(param('seed', config.non_negative_int, 0))
        self.pause = param('pause', config.non_negative_float, 0.02)
        self.name = rospy.get_name().strip('/').replace('/', '_')

    def setup(self, timeout):
        self.proxy = account_proxy(timeout)
        return self.proxy is not None

    def operation(self):
        """Deposits and withdrawals that keep the balance near zero, so that some withdrawals are
        refused for insufficient funds (the checker checks those refusals too)."""
        if self.rng.random() < 0.45:
            return 'withdraw', self.rng.randint(1, 20)
        return 'deposit', self.rng.randint(1, 10)

    def run(self):
        index = 0
        with open(self.history, 'a') as out:
            while not os.path.exists(self.stop_file) and not rospy.is_shutdown():
                op, amount = self.operation()
                tag = '%s:%d' % (self.name, index)
                out.write(json.dumps({'i': index, 'invoke': time.time(), 'op': op, 'amount': amount, 'tag': tag})
                          + '\n')
                out.flush()
                record = {'i': index}
                try:
                    reply = self.proxy(op=op, amount=amount, tag=tag)
                    record.update(outcome='ok', reply=[reply.balance, reply.count, reply.digest])
                except (rospy.ServiceException, rospy.ROSException) as e:
                    record.update(outcome=classify_error(str(e)), error=str(e)[:300])
                record['complete'] = time.time()
                out.write(json.dumps(record) + '\n')
                out.flush()
                index += 1
                if self.pause or record['outcome'] == 'not_executed':
                    time.sleep(self.pause or 0.02)
        return index
