"""btmission's performance shortcuts, in one place: each one, why it exists, what it saves, and
the contract it keeps (issue #35 item 8).

A shortcut is code that does what a library's or the language's ordinary way does, for less, by
doing it differently. Each lives here, next to the others, so that it is found, measured and
checked against what it stands in for; the package imports nothing of its own (the record
builder, which light modules use, does not load py_trees; the tick shortcuts do):

* :mod:`btmission.fastpaths.ticks` — the behaviour trees' tick (py_trees 2.x);
* :mod:`btmission.fastpaths.records` — the frozen dataclasses a run builds by the thousand.

The tests that pin each contract are in ``tests/unit/fastpaths/test_fastpaths.py`` (and, for the composites,
``tests/unit/synthesis/test_synthesis.py``'s random trees and ``tests/system/test_badinput_cli.py``'s dry runs). Times
below: the mine mission's agent tree (50 nodes, a task running) ticked 10,000 times after 300
run steps, Python 3.11 on this repository's shared 2-core machine (±10 % between runs).

1. **The statuses as module globals** (``ticks.RUNNING``, ``SUCCESS``, ``FAILURE``,
   ``INVALID``). On Python 3.11 reading an Enum member through its class costs about five times
   reading a global; composites and leaves read them on every tick. Contract: they *are*
   py_trees' ``Status`` members (compared with ``is``).

2. **LeanTick: a tick is a call, not a generator per behaviour** (``ticks.LeanTick``,
   ``ticks.tick_behaviour``; used by the composites below and by the runtime's leaves,
   :class:`btmission.runtime.leaves.GuardedLeaf` and its subclasses). py_trees' ``tick()`` is a
   generator per behaviour, each behaviour ticked below a composite is yielded up through every
   ancestor (O(depth) per node: a 1,000-action chain took seconds a tick), and every tick and
   stop formats a debug message. ``tick_now()`` runs the same steps as plain calls; ``tick()``
   still exists and yields the behaviour itself, once, at the end; ``iterator`` (the fresh tick
   generator py_trees keeps and never reads) is made when read. Saves: the mine tree's tick costs
   8.0 µs; with its leaves ticked by py_trees' own ``Behaviour.tick``/``stop`` 23-24 µs.
   Contract kept: the hooks py_trees documents for users — ``initialise`` (unless RUNNING),
   ``update``, ``terminate`` (through ``stop``, unless RUNNING) — are called in py_trees' order
   with py_trees' statuses. Where it departs, on purpose: iterating ``tick()`` yields the
   behaviour alone, not every one ticked below it (py_trees visitors that want those see only the
   root; btmission's, :class:`~btmission.runtime.treestatus.StatusChanges`, compares every node
   after the tick); and ``GuardedLeaf`` overrides ``Behaviour.tick`` and ``Behaviour.stop``,
   which py_trees' docstrings ask users not to override ("the update/terminate method has been
   provided for that purpose") — it keeps their documented effects, without the debug messages.
   :meth:`btmission.runtime.leaves.ConditionLeaf.tick_now` goes one step further for conditions
   (their ``initialise``/``terminate`` are no-ops: it inlines the update guard and skips them);
   it lives with its class, and a subclass that overrides a hook gets the full tick back.

3. **btmission's own reactive composites** (``ticks.QuietSelector``, ``ticks.QuietSequence``;
   built by :func:`btmission.synthesis.pytrees.build_behaviour_tree` with ``quiet=True``: the
   agents' trees and the dry run). They derive from py_trees' public base
   ``py_trees.composites.Composite``, whose ``tick`` is abstract ("All composite subclasses
   require a re-implementation of the tick method") and whose ``stop`` each composite overrides —
   py_trees allows custom composites ("It is possible and often desirable to extend this set
   with custom composites of your own"); they neither subclass its ``Selector``/``Sequence`` nor
   call into their internals. Their tick is py_trees' ``Selector``/``Sequence`` tick with
   ``memory=False`` (the only memory btmission's back-chained trees use; ``memory=True`` is
   refused) step for step, as LeanTick calls. Contract kept: every node's status and current
   child and every leaf hook call, tick by tick and across stops (tested against py_trees' own
   on a table of trees and on random ones). Departs: they are not ``isinstance`` of py_trees'
   ``Selector``/``Sequence`` (:func:`btmission.runtime.treestatus.node_kind` names them fallback
   and sequence, so the ``tree`` events are unchanged; ``py_trees.display`` draws them as plain
   composites); their ``stop`` does ``Composite.stop``'s documented work without its fresh tick
   generator (through ``Composite.stop`` the mine tree's tick costs 9.4-10 µs instead of 8.0).

4. **LeanBehaviourTree** (``ticks.LeanBehaviourTree``, the agents' tree custodian): py_trees'
   ``BehaviourTree.tick`` — pre-tick handlers, visitors, post-tick handlers, in its order — with
   the visitor lists made once per tick, not once per ticked behaviour, and the pass over the
   whole tree only for ``full`` visitors. Saves: the mine tree's tick with its status visitor and
   logger 7.8 µs; through ``BehaviourTree.tick`` 28 µs. Contract kept: ``tick()``'s signature and
   the calls it makes (a public method of a public class, overridden).

5. **The record builder** (``records.recorder``, re-exported by :mod:`btmission.types`; used for
   ``Telemetry``, ``Prediction``, ``AgentState``, ``Bid`` and ``PoolTask``). A frozen dataclass's
   ``__init__`` stores each field with ``object.__setattr__``; the builder stores them straight
   into the new instance's ``__dict__``. A 12-field ``Telemetry``: ``Telemetry(...)`` 1.54 µs, a
   builder without generated code 0.72 µs, the generated builder 0.38 µs — so the generated code
   stays, in one function (``records._keyword_builder``) whose source is made only of checked
   identifiers. Contract kept: an instance of the class equal to ``cls(**fields)`` (hash,
   ``repr``, ``replace``, pickling, frozenness its own) and the dataclass's ``TypeError`` for a
   missing or unknown field; a class whose ``__init__`` does more than store its fields (found
   through ``dataclasses.fields`` and ``inspect.signature`` only) is built by the class itself.

Not here, and why: Enum members kept as module globals in the modules that read them every step
(``backends/sim.py``, ``runtime/actions.py``; ``runtime/treestatus.py``'s status names) are plain
Python, with no contract at stake. Values derived once and memoised on frozen dataclasses
through ``self.__dict__`` and ``object.__setattr__`` (``allocation/auction.py``,
``allocation/solvers.py``, ``allocation/tasks.py``, ``links/wire.py``) are a cache, not a
shortcut past a contract (``functools.cached_property`` would be the library's spelling of it).
"""
