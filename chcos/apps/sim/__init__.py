"""sim - simulated slaves and cells that stand in for hardware (loopback and virtual CAN only)."""
