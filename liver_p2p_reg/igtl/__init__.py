"""OpenIGTLink link to 3D Slicer: wire format, Slicer's conventions, a non-blocking server and client."""
