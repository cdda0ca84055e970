"""rosbag2 bags without rosbag2 (on ``rosbags``): I/O, transitions from bags, and the bag executables.

* :mod:`.io`: read and write Jazzy rosbag2 bags (format 9, MCAP), with errors a user can act on;
* :mod:`.transitions`: the transitions in a bag, paired exactly as the online learner pairs them (no rclpy);
* :mod:`.info`: ``bag_info`` (what a bag holds, its transitions, a model-error plot);
* :mod:`.record` / :mod:`.play`: ``record`` and ``play`` (rclpy).

Modules are imported by name; this face imports nothing (``record`` and ``play`` need rclpy, the rest do not).
"""
