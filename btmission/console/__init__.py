"""The operator console: add, cancel and reprioritise tasks, recall and exclude agents, pause
allocation, in a running mission, from the viewer page, the HTTP/JSON API or the CLI
(docs/operator.md).

* :mod:`btmission.console.service`: the logic (checks, commands, results, rate limits), no HTTP;
* :mod:`btmission.console.api`: the routes and the guard (token, origin, size, rate);
* :mod:`btmission.console.client`: the client the CLI (``btmission task``, ``status``,
  ``fleet``) uses.
"""
