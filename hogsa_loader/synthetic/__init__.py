"""The generated ARCTIC- and H2O-format test world: world generator, procedural objects, synthetic
MANO-schema hand and H2O writer. The library never imports this package; tests, the demo and
``hogsa world`` do."""
