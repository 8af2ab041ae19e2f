"""The live web dashboard of ``upright dashboard``: a page served on 127.0.0.1 from the project.

* :mod:`host.dashboard.hub` -- :class:`~host.dashboard.hub.Hub`: one thread owns the board's
  link and fans every message out (telemetry rows stamped with their receive time, heartbeats,
  replies); commands from any thread go through that same :class:`~host.link.clients.Link`,
  shared (:meth:`~host.link.clients.Link.share`: the pump reads, commands wait for what the hub
  delivers); the watchdog policy (the host heartbeat is fed
  only while a live page asked for the arm; the last page gone -> disarm); recording to CSV;
* :mod:`host.dashboard.plant` -- ``--virtual``: the firmware's HIL main on a pty
  (:class:`host.hil.session.HilSession`) closed around the simulated plant by THE lockstep loop
  (:class:`host.hil.lockstep.Lockstep`), paced to the wall clock in a background thread;
* :mod:`host.dashboard.gains` -- the gain tables the page offers (the shipped design, a file);
* :mod:`host.dashboard.server` -- the HTTP server (stdlib ``http.server``): the page, its
  assets (uPlot from ``node_modules``: nothing from a CDN), Server-Sent Events, a small JSON API;
  commands only with this run's token (in the printed address and the page it served);
* :mod:`host.dashboard.request` -- what a request must look like (its length, its JSON, each
  field's type and range): every malformed one refused in one line before it reaches the board;
* ``static/`` -- the page; ``e2e.mjs`` -- the browser test's driver (playwright-core).
"""
