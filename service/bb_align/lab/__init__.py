"""Measuring the method and the service: the simulator (``sim``), ``bb-align eval`` (``evaluation``),
``bb-align bench`` (``bench``), the hostile-traffic soak, the live demo and the harness they share (free ports,
child processes, memory readings, simulated cars). May import anything; nothing imports it but the CLI."""
