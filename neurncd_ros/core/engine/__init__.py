"""The online engine: the stages the ROS nodes and the offline tools both drive.

``records`` holds the typed records passed between the stages.
"""
