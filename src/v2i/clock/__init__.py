"""Clock synchronisation (pure): RSU offset and drift from NTP-style four-timestamp exchanges."""
