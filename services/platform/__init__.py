"""What only the lab platform needs, shared by the api, the worker, the client and the CLI.

For now the job contract (:mod:`services.platform.jobs`): each job kind's config model, the
one validation of a job's config, and its display summary. sim, eeg and learner never
import this package.
"""
