"""The inference engines, one module each (their names: :data:`bayesdrive.inference.fit.ENGINES`)."""
