"""The registration core: every stage from preprocessing to the result, and the table of methods; never imports ROS."""
