"""What the viewer computes about a run, without drawing it: the failure list
(``failures``: ranked problems, notes), Kalman filter runs over the sequence
(``filter_runs``: filter A from the results, B re-filtered) and the filter panel's trace
plot (``trace_plot``, an off-screen matplotlib figure), each view's part in one joint
(``joint_views``: the Selection tab's "why is this joint here"). May import
:mod:`mvviz.scene` (its plain data) and ``pipeline``; never the panels, the app or the
command line.
"""
