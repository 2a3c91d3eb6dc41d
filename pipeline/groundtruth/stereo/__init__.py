"""The ``vo`` ground-truth method, stereo visual odometry: the algorithm on arrays (``stereo_vo``), its
options, camera and statistics (``vo_settings``), a bag's stereo pairs (``stereo_bag``) and the method's
entry point (``vo``: :func:`~.vo.run_stereo_vo`)."""
