"""``fmapping up``: run the multi-process system on one machine.

Starts, as separate OS processes (``sys.executable -m services...``):

* ``services.mapper`` (first),
* ``services.io record`` (OUT/record/: traj_<source>.txt, points.ply),
* ``services.io view --save OUT/run.rrd`` (rerun recording; ``--view live`` also serves rerun's
  web viewer on ``--view-port`` / ``--grpc-port`` and prints its URL),
* ``services.tracker`` when ``--poses tracker``,
* ``services.io play`` last (it waits until the others report, then streams the data).

Networking is secure by default (:mod:`services.credentials`, docs/security.md): the launcher
makes per-run credentials (a random password per role, files 0600 in OUT/secrets, deleted at
the end) and starts a zenoh router (``services.router``) on a free loopback port that admits
only those users and lets each role publish, subscribe and ask only its own keys; every
service is a client of it, in a namespace of its own (``fmapping/up<pid>/...``). With
``--insecure`` (local debugging) it is the old open peer mesh instead: each process listens
on a free ``tcp/127.0.0.1:<port>`` and connects to every process started before it. Each process logs
to OUT/logs/<name>.log and writes its status to OUT/status/<name>.json, which the launcher
reads to show progress. At the end of the sequence play sends the end-of-sequence stop;
the mapper runs its closing stage and writes OUT/map.ply, OUT/mesh.ply, OUT/traj.txt and
OUT/stats.json; record and view finish after it. A mapper, tracker, recorder or viewer that
crashes while play streams is started again (at most 3 times, backoff 1, 2, 4 s; counted in
OUT/up.json ``restarts``); the mapper resumes from its checkpoint, the mono tracker re-localises
against its saved keyframes (OUT/tracker/state.npz), and play sends a restarted service the frames
it never handled (``io play --resend-to``). ``fmapping up --resume OUT`` continues a run whose
launcher was killed (its arguments are in OUT/run.json). Ctrl-C (or SIGTERM) stops
every process (SIGINT, then SIGKILL after a grace period); the mapper still writes its current map.

This package only starts processes and reads files: it does not import zenoh.
With ``--poses external`` a producer must publish ``Pose(source="external")`` (see
``examples/publish_poses.py``; the launcher prints the command); play waits for it.

``--config`` YAML: either mapper overrides at the top level (like ``fmapping map``), or
sections ``mapper:``, ``tracker:`` and ``launcher:`` (keys: ``timeout`` seconds,
``view`` true/false, ``window`` frames in flight, ``frames`` / ``size`` / ``seed`` of
the generated scene, ``threads`` per torch process, ``tracker_frontend`` mono|map).

With ``--poses tracker`` the tracker's default front end is ``mono`` (RGB only from the
first frame, world frame and scale from the first GT poses that play publishes, exactly
as ``fmapping slam``); the mapper takes its poses as given. ``tracker_frontend: map`` runs
the paper-style loop instead: the mapper initialises without poses (``--unposed-init yes``)
and the tracker follows its field.

The pieces: :mod:`services.launcher.up` (the run), :mod:`~services.launcher.commands` (the services'
command lines, written by their own parsers), :mod:`~services.launcher.supervise` (the child
processes), :mod:`~services.launcher.resume` (``--resume``), :mod:`~services.launcher.demo`
(``fmapping demo``); the config file's sections in :mod:`fmapping.up_config`; the sub-commands in
:mod:`services.cli`.
"""
