"""The FastAPI labelling service: operator REST, labeller API and clip serving.

It talks to the trainer only through the queue database (`labelqueue`) and never imports
`trainer` or `torch`. Build the app with `server.app.create_app(settings)`.
"""
