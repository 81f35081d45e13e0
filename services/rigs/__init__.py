"""Real rigs: the conformance kit, record and replay (MCAP), surveys."""
