"""The ``lanefree`` verbs: one module each (``simulate``, ``train``, ``evaluate``, ``replay``, ``export``,
``report``, ``config``, ``net``), each with its options declared once (:class:`~lanefree_sumo.options.Option`),
its ``add_parser`` and its ``run``. ``rollout``, ``sweep`` and ``mixed-autonomy`` own theirs beside their work in
:mod:`lanefree_sumo.experiments`. The work itself is in :mod:`lanefree_sumo.experiments`.
"""
