"""The generic link: contracts, the owner-task engine, capture, validation."""
