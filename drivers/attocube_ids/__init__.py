"""attocube IDS displacement interferometers over their JSON-RPC 2.0 API on TCP."""
