"""REN controllers (`controller`), their direct parameterisation (`map`) and their
certificate (`certify`)."""
