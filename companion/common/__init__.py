"""What every layer of the companion shares: the one-line user error, TOML reading and user-file checks.

Imports nothing else of the companion, so any module may import it."""
