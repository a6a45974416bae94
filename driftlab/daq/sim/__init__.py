"""The virtual machine tool and its simulated instrument transports."""
