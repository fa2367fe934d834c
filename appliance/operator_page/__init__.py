"""The operator page: a read-only view of the daemon in a browser, on 127.0.0.1.

``OperatorPage`` (server.py) serves the page (static/index.html), the daemon's status
document and its last scans (scans.py); http.py is its sans-I/O HTTP.
"""

from appliance.operator_page.scans import scans_document
from appliance.operator_page.server import OperatorPage

__all__ = ["OperatorPage", "scans_document"]
