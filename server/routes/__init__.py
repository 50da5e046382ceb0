"""The API's routers: operator (`runs`, `labellers`) and labeller (`label`, clips)."""
