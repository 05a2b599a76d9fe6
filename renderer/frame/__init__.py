"""One frame: the plan (what a launch needs), its preparation on the host, the launch and report, and adaptive screen-space sampling's tiles."""
