"""The drivers: authoring a plan, one render job, the dispatcher and its worker, the demo."""
