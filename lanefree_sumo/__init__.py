"""lanefree_sumo: deep RL in lane-free traffic on Eclipse SUMO."""
