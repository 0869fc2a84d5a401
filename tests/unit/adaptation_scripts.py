"""Adaptation scripts the unit tests share (test data)."""

COMPOSE = """
name: compose
kind: compose
args: {site: [master, slave], mechanism: tr}
each: site
suspend: [/$(arg site)/protocol]
launch:
  - file: aft_ftm/mechanism.launch
    args: {ns: /$(arg site)/$(arg mechanism), bind_input: false}
bind:
  - {node: /$(arg site)/proceed, port: inp, unbind: true}
  - {node: /$(arg site)/$(arg mechanism)/protocol, port: requests, topic: /$(arg site)/bfr2prd}
retire: [/$(arg site)/proceed]
"""

# The same, promoting the new nodes' roles through each site's Recovery.
COMPOSE_PROMOTING = COMPOSE.replace('retire:', """promote:
  - {recovery: /$(arg site)/recovery, nodes: [/$(arg site)/before, /$(arg site)/$(arg mechanism)/after]}
retire:""")
