"""A login flood from a process of its own (``test_flood.py`` in tests/integration/auth/
starts it).

``python tests/support/login_flood.py BASE_URL COUNT ADDRESS``: COUNT concurrent
``POST /api/auth/login`` with unknown names, each sent as from ADDRESS (the server
trusts ``X-Forwarded-For`` from 127.0.0.1 in the test). Prints ``started`` once every
request is on its way, then one status code per line as the answers come in.
"""

from __future__ import annotations

import asyncio
import sys

import httpx


async def flood(base_url: str, count: int, address: str) -> None:
    limits = httpx.Limits(max_connections=count)
    async with httpx.AsyncClient(base_url=base_url, timeout=600, limits=limits) as http:

        async def one(index: int) -> None:
            response = await http.post(
                "/api/auth/login",
                json={"user": f"nobody{index}", "password": "guess-guess-guess"},
                headers={"X-Forwarded-For": address},
            )
            print(response.status_code, flush=True)

        tasks = [asyncio.create_task(one(i)) for i in range(count)]
        print("started", flush=True)
        await asyncio.gather(*tasks)


if __name__ == "__main__":
    asyncio.run(flood(sys.argv[1], int(sys.argv[2]), sys.argv[3]))
