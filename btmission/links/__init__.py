"""Links between the coordinator and its agents: the messages and their two ends
(:mod:`btmission.links.bus`: ``CoordinatorLink``, ``AgentLink``, the in-memory bus of one
process), and the versioned wire form every message has (:mod:`btmission.links.wire`), which a
network transport (:mod:`btmission.transport`: Eclipse Zenoh) carries unchanged."""
