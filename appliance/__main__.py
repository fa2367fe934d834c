"""`python -m appliance` is `dbw`."""

from appliance.cli import main

main()
