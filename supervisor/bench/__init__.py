"""The lab: benchmarks, fault injection and load generators (``supervisor bench …``).

Not part of the product: a layer above the composition root (``supervisor.app``), whose
public surface it builds benches with, and below the command line. No product package
imports it (import-linter contract "The product never imports its lab"). Importing this
package imports none of its modules: ``supervisor run`` takes only ``memtrace``, its
memory tracing switch.
"""
