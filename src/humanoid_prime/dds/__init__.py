"""Prime on the ROS 2 graph: DDS with ROS 2's wire conventions (``rt/`` topics, ``pkg::msg::dds_::Type_`` type
names, XCDR1, ROS 2's QoS), through Cyclone DDS. Opt-in: nothing here is imported unless a run asks for DDS."""
