"""The TOML models of the experiment file, on one strict base."""
