"""Built-in CoEx transports (Micromodem, MAVLink, LCM); each registers through entry points."""
