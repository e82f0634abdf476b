"""``packml conform``: a PackML conformance kit for any target, a ROS unit or an OPC 30050 server.

- :mod:`.expect`: what the standard expects (the rule book compiled for the declared model);
- :mod:`.plan`: the checks of each profile;
- :mod:`.runner`: drives a target through them and judges (pure: the target is the face);
- :mod:`.target`: what a target offers; :mod:`.ros_target`, :mod:`.opcua_target`: the faces;
- :mod:`.report`: the table, JSON and JUnit XML.
"""
